//! The pure image step of a slice view: stored values → physical values (the store's value
//! mapping) → the window (black at its low end, white at its high end) → a colour map, as
//! RGBA8 pixels. Both viewers colour slices through this one function, so a slice looks the
//! same on the desktop and in the browser. Also the window-dragging gesture both share.

use serde::{Deserialize, Serialize};
use strata_types::ValueMapping;

use crate::colour_maps::ColourMap;

/// A slice window in physical units (HU for CT): values from `centre - width/2` (black) to
/// `centre + width/2` (white).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Window {
    pub centre: f64,
    pub width: f64,
}

impl Window {
    pub fn new(centre: f64, width: f64) -> Self {
        Window { centre, width }
    }

    pub fn low(&self) -> f64 {
        self.centre - self.width * 0.5
    }
}

/// Stored values → RGBA8 (4 bytes a pixel, opaque) through the window and the colour map.
pub fn window_level_rgba(
    values: &[u16],
    window: Window,
    colour_map: ColourMap,
    mapping: ValueMapping,
) -> Vec<u8> {
    let lo = window.low();
    let scale = 255.0 / window.width.max(1e-9);
    let table = colour_map.table();
    let mut rgba = Vec::with_capacity(values.len() * 4);
    for &s in values {
        let g = ((mapping.physical(s as f64) - lo) * scale).clamp(0.0, 255.0) as usize;
        let [r, g, b] = table[g];
        rgba.extend_from_slice(&[r, g, b, 255]);
    }
    rgba
}

/// Dragging the window (the desktop's right drag): sideways by `dx` points widens (right) or
/// narrows it, up (negative `dy`) raises the level. The gain follows the window itself (a drag
/// across 300 points multiplies the width by e, moves the level by one width), so a narrow
/// brain window and a wide bone window feel the same; a floor of 1/500 of the scan's range
/// keeps a collapsed window recoverable.
pub fn drag_window(window: Window, dx: f64, dy: f64, physical_range: (f64, f64)) -> Window {
    let (lo, hi) = physical_range;
    let floor = ((hi - lo).abs() / 500.0).max(1e-6);
    let width = window.width.max(floor);
    Window::new(
        window.centre - dy * width / 300.0,
        (width * (dx / 300.0).exp()).max(floor),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_ends_map_to_black_and_white() {
        // CT: physical = stored - 1024. Window 40 ± 40 HU: -0 .. 80 HU.
        let mapping = ValueMapping {
            slope: 1.0,
            intercept: -1024.0,
        };
        let window = Window::new(40.0, 80.0);
        let stored = |hu: f64| (hu + 1024.0) as u16;
        let values = [
            stored(0.0),
            stored(80.0),
            stored(-500.0),
            stored(900.0),
            stored(40.0),
        ];
        let rgba = window_level_rgba(&values, window, ColourMap::Grey, mapping);
        let px = |i: usize| {
            [
                rgba[4 * i],
                rgba[4 * i + 1],
                rgba[4 * i + 2],
                rgba[4 * i + 3],
            ]
        };
        assert_eq!(px(0), [0, 0, 0, 255], "the low end is black");
        assert_eq!(px(1), [255, 255, 255, 255], "the high end is white");
        assert_eq!(px(2), [0, 0, 0, 255], "below the window clamps to black");
        assert_eq!(
            px(3),
            [255, 255, 255, 255],
            "above the window clamps to white"
        );
        assert_eq!(px(4), [127, 127, 127, 255], "the centre is mid grey");
        // Inverted swaps the ends; the slope counts (MR-like mapping, slope 2).
        let inverted = window_level_rgba(&values[..2], window, ColourMap::Inverted, mapping);
        assert_eq!(&inverted[..4], &[255, 255, 255, 255]);
        let doubled = ValueMapping {
            slope: 2.0,
            intercept: 0.0,
        };
        let rgba = window_level_rgba(&[20, 60], Window::new(80.0, 80.0), ColourMap::Grey, doubled);
        assert_eq!((rgba[0], rgba[4]), (0, 255));
    }

    #[test]
    fn window_drag_gain_follows_the_window_not_the_scan_range() {
        let ct_range = (-1024.0, 3071.0);
        // 100 points right: the same factor for a brain and a bone window (e^(1/3) ≈ 1.40),
        // where the old gain added ~1300 HU to either.
        for width in [80.0, 2000.0] {
            let w = drag_window(Window::new(40.0, width), 100.0, 0.0, ct_range);
            let factor = w.width / width;
            assert!(
                (factor - (1.0f64 / 3.0).exp()).abs() < 1e-9,
                "{width}: ×{factor}"
            );
            assert_eq!(w.centre, 40.0);
        }
        // 30 points up raises the level by a tenth of the width.
        let w = drag_window(Window::new(40.0, 400.0), 0.0, -30.0, ct_range);
        assert!((w.centre - 80.0).abs() < 1e-9 && w.width == 400.0);
        // Dragging left for ever never collapses the window below the floor.
        let mut w = Window::new(0.0, 10.0);
        for _ in 0..100 {
            w = drag_window(w, -300.0, 0.0, ct_range);
        }
        assert!(w.width >= 4095.0 / 500.0 - 1e-9);
    }
}
