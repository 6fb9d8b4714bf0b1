//! Where the views go in each layout, shared by the desktop viewer and the browser page (issue
//! 47 item 3: the page gets the desktop's layouts by sharing this code): the 2×2 ("four-up":
//! axial, 3D / sagittal, coronal) and the 3D view over a row of slices (Slicer's
//! "conventional"). Pure geometry: each caller puts its own views in the cells.
//!
//! Tested here (the cells tile the area without overlap) and in Chromium by
//! web/tests/browser.rs (`the_page_shows_the_3d_view_over_its_slices_as_the_desktop_does`).

use egui::{Pos2, Rect, Vec2};

/// The gap between two views (points).
pub const VIEW_GAP: f32 = 2.0;

/// The share of the height the 3D view takes above the row of slices: the 3D view is the one
/// that needs the area, the slices stay wide enough to read.
pub const THREE_D_SHARE: f32 = 0.62;

/// The 2×2 cells of `area`, row by row: top left, top right, bottom left, bottom right.
pub fn two_by_two_cells(area: Rect) -> [Rect; 4] {
    let (w, h) = (
        (area.width() - VIEW_GAP) / 2.0,
        (area.height() - VIEW_GAP) / 2.0,
    );
    let cell = |c: f32, r: f32| {
        Rect::from_min_size(
            Pos2::new(
                area.left() + c * (w + VIEW_GAP),
                area.top() + r * (h + VIEW_GAP),
            ),
            Vec2::new(w, h),
        )
    };
    [
        cell(0.0, 0.0),
        cell(1.0, 0.0),
        cell(0.0, 1.0),
        cell(1.0, 1.0),
    ]
}

/// The 3D view on top of `area` and `columns` views in a row below it, left to right.
pub fn three_d_over_row(area: Rect, columns: usize) -> (Rect, Vec<Rect>) {
    let split = area.top() + area.height() * THREE_D_SHARE;
    let top = Rect::from_min_max(area.min, Pos2::new(area.right(), split - VIEW_GAP));
    let count = columns.max(1) as f32;
    let w = (area.width() - (count - 1.0) * VIEW_GAP) / count;
    let row = (0..columns)
        .map(|i| {
            let left = area.left() + i as f32 * (w + VIEW_GAP);
            Rect::from_min_max(Pos2::new(left, split), Pos2::new(left + w, area.bottom()))
        })
        .collect();
    (top, row)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every layout's cells lie inside the area, overlap nowhere and leave only the gaps.
    #[test]
    fn the_cells_of_each_layout_tile_the_area_without_overlap() {
        let area = Rect::from_min_size(Pos2::new(10.0, 20.0), Vec2::new(802.0, 602.0));
        let (top, row) = three_d_over_row(area, 3);
        let mut layouts = vec![two_by_two_cells(area).to_vec(), {
            let mut cells = vec![top];
            cells.extend(row);
            cells
        }];
        let (top, row) = three_d_over_row(area, 4);
        layouts.push([vec![top], row].concat());
        for cells in layouts {
            let covered: f32 = cells.iter().map(|c| c.area()).sum();
            for (i, a) in cells.iter().enumerate() {
                assert!(area.contains_rect(*a), "{a:?} outside {area:?}");
                assert!(a.width() > 0.0 && a.height() > 0.0, "{a:?} is empty");
                for b in &cells[i + 1..] {
                    assert!(!a.intersects(*b), "{a:?} overlaps {b:?}");
                }
            }
            // Only the gaps are left: under 2 % of the area for these sizes.
            assert!(covered > 0.98 * area.area(), "{covered} of {}", area.area());
        }
        // The 3D view on top takes its share of the height.
        let (top, row) = three_d_over_row(area, 3);
        assert!((top.height() + VIEW_GAP - THREE_D_SHARE * area.height()).abs() < 1e-3);
        assert!(row.iter().all(|r| r.top() > top.bottom()));
    }
}
