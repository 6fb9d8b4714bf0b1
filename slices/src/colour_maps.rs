//! Colour maps for slices: grey, inverted grey, hot, turbo (Google's perceptual rainbow, the
//! usable "jet") and viridis (matplotlib's perceptually uniform default). Turbo and viridis are
//! their published polynomial fits (viridis within 5/255 of matplotlib's table; turbo's
//! fit is darker than its table at the very ends).

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum ColourMap {
    #[default]
    Grey,
    Inverted,
    Hot,
    Turbo,
    Viridis,
}

impl ColourMap {
    pub const ALL: [ColourMap; 5] = [
        ColourMap::Grey,
        ColourMap::Inverted,
        ColourMap::Hot,
        ColourMap::Turbo,
        ColourMap::Viridis,
    ];

    pub fn label(self) -> &'static str {
        match self {
            ColourMap::Grey => "Grey",
            ColourMap::Inverted => "Inverted",
            ColourMap::Hot => "Hot",
            ColourMap::Turbo => "Turbo",
            ColourMap::Viridis => "Viridis",
        }
    }

    /// The colour at `t` ∈ [0, 1] (clamped), 8 bits per channel.
    pub fn rgb(self, t: f64) -> [u8; 3] {
        let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
        let c = match self {
            ColourMap::Grey => [t, t, t],
            ColourMap::Inverted => [1.0 - t, 1.0 - t, 1.0 - t],
            // Black → red → yellow → white, each channel ramping over a third.
            ColourMap::Hot => [
                (3.0 * t).min(1.0),
                (3.0 * t - 1.0).clamp(0.0, 1.0),
                (3.0 * t - 2.0).clamp(0.0, 1.0),
            ],
            ColourMap::Turbo => turbo(t),
            ColourMap::Viridis => viridis(t),
        };
        c.map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)
    }

    /// A 256-entry lookup table (a slice is coloured by index, not by polynomial per pixel).
    pub fn table(self) -> [[u8; 3]; 256] {
        let mut table = [[0u8; 3]; 256];
        for (i, entry) in table.iter_mut().enumerate() {
            *entry = self.rgb(i as f64 / 255.0);
        }
        table
    }
}

/// Anton Mikhailov's polynomial approximation of Turbo (Google AI blog, 2019).
fn turbo(t: f64) -> [f64; 3] {
    let (t2, t3, t4, t5) = (t * t, t * t * t, t.powi(4), t.powi(5));
    [
        0.13572138 + 4.61539260 * t - 42.66032258 * t2 + 132.13108234 * t3 - 152.94239396 * t4
            + 59.28637943 * t5,
        0.09140261 + 2.19418839 * t + 4.84296658 * t2 - 14.18503333 * t3
            + 4.27729857 * t4
            + 2.82956604 * t5,
        0.10667330 + 12.64194608 * t - 60.58204836 * t2 + 110.36276771 * t3 - 89.90310912 * t4
            + 27.34824973 * t5,
    ]
}

/// Matt Zucker's degree-6 polynomial fit of viridis (shadertoy WlfXRN).
fn viridis(t: f64) -> [f64; 3] {
    const C: [[f64; 3]; 7] = [
        [0.2777273272234177, 0.005407344544966578, 0.3340998053353061],
        [0.1050930431085774, 1.404613529898575, 1.384590162594685],
        [-0.3308618287255563, 0.214847559468213, 0.09509516302823659],
        [-4.634230498983486, -5.799100973351585, -19.33244095627987],
        [6.228269936347081, 14.17993336680509, 56.69055260068105],
        [4.776384997670288, -13.74514537774601, -65.35303263337234],
        [-5.435455855934631, 4.645852612178535, 26.3124352495832],
    ];
    let mut out = [0.0; 3];
    for (channel, o) in out.iter_mut().enumerate() {
        *o = C.iter().rev().fold(0.0, |acc, c| acc * t + c[channel]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_hit_their_published_end_points() {
        assert_eq!(ColourMap::Grey.rgb(0.0), [0, 0, 0]);
        assert_eq!(ColourMap::Grey.rgb(1.0), [255, 255, 255]);
        assert_eq!(ColourMap::Inverted.rgb(0.0), [255, 255, 255]);
        assert_eq!(ColourMap::Hot.rgb(0.0), [0, 0, 0]);
        assert_eq!(ColourMap::Hot.rgb(1.0 / 3.0), [255, 0, 0]);
        assert_eq!(ColourMap::Hot.rgb(1.0), [255, 255, 255]);
        // viridis: #440154 at 0, #21918c near 0.5, #fde725 at 1 (matplotlib's table).
        let near = |a: [u8; 3], b: [u8; 3]| a.iter().zip(b).all(|(x, y)| x.abs_diff(y) <= 5);
        assert!(near(ColourMap::Viridis.rgb(0.0), [0x44, 0x01, 0x54]));
        assert!(near(ColourMap::Viridis.rgb(0.5), [0x21, 0x91, 0x8c]));
        assert!(near(ColourMap::Viridis.rgb(1.0), [0xfd, 0xe7, 0x25]));
        // turbo: dark at 0, green-yellow in the middle, dark red at 1.
        assert!(ColourMap::Turbo.rgb(0.0).iter().all(|x| *x < 64));
        let mid = ColourMap::Turbo.rgb(0.55);
        assert!(mid[1] > 200 && mid[1] > mid[2], "{mid:?}");
        let end = ColourMap::Turbo.rgb(1.0);
        assert!(end[0] > 100 && end[1] < 30 && end[2] < 30, "{end:?}");
        // Out of range and NaN clamp.
        assert_eq!(ColourMap::Grey.rgb(-3.0), [0, 0, 0]);
        assert_eq!(ColourMap::Grey.rgb(f64::NAN), [0, 0, 0]);
    }

    #[test]
    fn viridis_gets_brighter_along_the_map() {
        let luma = |c: [u8; 3]| 0.2126 * c[0] as f64 + 0.7152 * c[1] as f64 + 0.0722 * c[2] as f64;
        let table = ColourMap::Viridis.table();
        for i in 1..256 {
            assert!(luma(table[i]) + 1.0 >= luma(table[i - 1]), "at {i}");
        }
    }
}
