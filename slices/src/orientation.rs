//! Patient orientation of the slice views: which index axis runs across, down and through
//! each view, so a scan stored in any axis order or with flipped axes shows the patient the
//! radiological way (patient right on screen left; anterior up in axial; superior up in
//! coronal and sagittal; anterior on the left in sagittal, as in 3D Slicer).
//!
//! An oblique scan shows its index plane closest to the anatomical one (no resampling); the
//! labels then name the nearest anatomical direction.

use glam::DVec3;
use serde::{Deserialize, Serialize};
use strata_types::VolumeGeometry;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum SliceView {
    Axial,
    Coronal,
    Sagittal,
}

impl SliceView {
    pub const ALL: [SliceView; 3] = [SliceView::Axial, SliceView::Coronal, SliceView::Sagittal];

    pub fn name(self) -> &'static str {
        match self {
            SliceView::Axial => "Axial",
            SliceView::Coronal => "Coronal",
            SliceView::Sagittal => "Sagittal",
        }
    }

    pub fn index(self) -> usize {
        match self {
            SliceView::Axial => 0,
            SliceView::Coronal => 1,
            SliceView::Sagittal => 2,
        }
    }

    /// LPS directions of screen right and screen down.
    fn screen_directions(self) -> (DVec3, DVec3) {
        let (l, p, i) = (DVec3::X, DVec3::Y, -DVec3::Z);
        match self {
            SliceView::Axial => (l, p),
            SliceView::Coronal => (l, i),
            SliceView::Sagittal => (p, i),
        }
    }
}

/// How one slice view maps index axes to the screen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SliceFrame {
    /// Index axis the view pages through.
    pub normal_axis: usize,
    /// Index axis running left→right on screen, and whether index grows leftwards.
    pub across_axis: usize,
    pub across_flipped: bool,
    /// Index axis running top→bottom on screen, and whether index grows upwards.
    pub down_axis: usize,
    pub down_flipped: bool,
    /// Labels at the left, right, top and bottom edges.
    pub labels: [&'static str; 4],
}

/// For each LPS axis, the index axis most aligned with it: the permutation maximising the
/// summed alignment, so two patient axes never claim the same index axis.
pub fn index_axis_of_patient_axes(geometry: &VolumeGeometry) -> [usize; 3] {
    const PERMUTATIONS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let alignment = |patient: usize, index: usize| geometry.direction[index][patient].abs();
    let mut best = PERMUTATIONS[0];
    let mut best_score = f64::NEG_INFINITY;
    for p in PERMUTATIONS {
        let score: f64 = (0..3).map(|patient| alignment(patient, p[patient])).sum();
        if score > best_score + 1e-12 {
            best = p;
            best_score = score;
        }
    }
    best
}

/// The patient direction (L, R, P, A, S, I) an LPS vector points to most.
pub fn label_of(direction: DVec3) -> &'static str {
    let a = direction.abs();
    if a.x >= a.y && a.x >= a.z {
        if direction.x > 0.0 {
            "L"
        } else {
            "R"
        }
    } else if a.y >= a.z {
        if direction.y > 0.0 {
            "P"
        } else {
            "A"
        }
    } else if direction.z > 0.0 {
        "S"
    } else {
        "I"
    }
}

fn patient_axis_of(direction: DVec3) -> usize {
    let a = direction.abs();
    if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    }
}

impl SliceFrame {
    pub fn for_view(view: SliceView, geometry: &VolumeGeometry) -> SliceFrame {
        let axis_of = index_axis_of_patient_axes(geometry);
        let (right, down) = view.screen_directions();
        let across_axis = axis_of[patient_axis_of(right)];
        let down_axis = axis_of[patient_axis_of(down)];
        let normal_axis = 3 - across_axis - down_axis;
        let dir = |a: usize| DVec3::from(geometry.direction[a]);
        let across_flipped = dir(across_axis).dot(right) < 0.0;
        let down_flipped = dir(down_axis).dot(down) < 0.0;
        // Labels name where the index axes really point, so an oblique scan is labelled honestly.
        let screen_right = if across_flipped {
            -dir(across_axis)
        } else {
            dir(across_axis)
        };
        let screen_down = if down_flipped {
            -dir(down_axis)
        } else {
            dir(down_axis)
        };
        SliceFrame {
            normal_axis,
            across_axis,
            across_flipped,
            down_axis,
            down_flipped,
            labels: [
                label_of(-screen_right),
                label_of(screen_right),
                label_of(-screen_down),
                label_of(screen_down),
            ],
        }
    }

    /// Level-0 continuous index along `across_axis`/`down_axis` of a point at fractions
    /// (u, v) ∈ [0,1]² of the displayed volume extent.
    pub fn index_at(&self, dims: [u32; 3], u: f64, v: f64) -> (f64, f64) {
        let u = if self.across_flipped { 1.0 - u } else { u };
        let v = if self.down_flipped { 1.0 - v } else { v };
        (
            u * dims[self.across_axis] as f64 - 0.5,
            v * dims[self.down_axis] as f64 - 0.5,
        )
    }

    /// Inverse of [`SliceFrame::index_at`].
    pub fn fraction_of(&self, dims: [u32; 3], across_index: f64, down_index: f64) -> (f64, f64) {
        let u = (across_index + 0.5) / dims[self.across_axis] as f64;
        let v = (down_index + 0.5) / dims[self.down_axis] as f64;
        (
            if self.across_flipped { 1.0 - u } else { u },
            if self.down_flipped { 1.0 - v } else { v },
        )
    }

    /// Millimetres the view spans across and down (the displayed aspect ratio).
    pub fn extent_mm(&self, geometry: &VolumeGeometry) -> (f64, f64) {
        (
            geometry.dims[self.across_axis] as f64 * geometry.spacing_mm[self.across_axis],
            geometry.dims[self.down_axis] as f64 * geometry.spacing_mm[self.down_axis],
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry(direction: [[f64; 3]; 3]) -> VolumeGeometry {
        VolumeGeometry {
            dims: [10, 20, 30],
            spacing_mm: [1.0, 1.0, 1.0],
            origin_lps_mm: [0.0; 3],
            direction,
        }
    }

    #[test]
    fn lps_stored_scan_shows_radiological_convention() {
        let g = geometry([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let axial = SliceFrame::for_view(SliceView::Axial, &g);
        assert_eq!(
            (axial.normal_axis, axial.across_axis, axial.down_axis),
            (2, 0, 1)
        );
        assert!(!axial.across_flipped && !axial.down_flipped);
        assert_eq!(axial.labels, ["R", "L", "A", "P"]);
        let coronal = SliceFrame::for_view(SliceView::Coronal, &g);
        assert_eq!(
            (coronal.normal_axis, coronal.across_axis, coronal.down_axis),
            (1, 0, 2)
        );
        assert!(coronal.down_flipped, "superior (+z) must be up");
        assert_eq!(coronal.labels, ["R", "L", "S", "I"]);
        let sagittal = SliceFrame::for_view(SliceView::Sagittal, &g);
        assert_eq!(
            (
                sagittal.normal_axis,
                sagittal.across_axis,
                sagittal.down_axis
            ),
            (0, 1, 2)
        );
        assert_eq!(sagittal.labels, ["A", "P", "S", "I"]);
    }

    #[test]
    fn ras_stored_and_permuted_scans_show_the_patient_the_same_way() {
        // RAS storage (as NIfTI often is): i → R (= -L), j → A (= -P), k → S.
        let ras = geometry([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]);
        let axial = SliceFrame::for_view(SliceView::Axial, &ras);
        assert!(axial.across_flipped && axial.down_flipped);
        assert_eq!(axial.labels, ["R", "L", "A", "P"]);
        // Sagittal acquisition: i → A→P... stored as i = -y (anterior), j = -z, k = x.
        let permuted = geometry([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]);
        let axial = SliceFrame::for_view(SliceView::Axial, &permuted);
        assert_eq!(
            (axial.normal_axis, axial.across_axis, axial.down_axis),
            (1, 2, 0)
        );
        assert_eq!(axial.labels, ["R", "L", "A", "P"]);
        let sagittal = SliceFrame::for_view(SliceView::Sagittal, &permuted);
        assert_eq!(sagittal.normal_axis, 2);
        assert_eq!(sagittal.labels, ["A", "P", "S", "I"]);
    }

    #[test]
    fn fractions_and_indices_round_trip() {
        let ras = geometry([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]);
        let f = SliceFrame::for_view(SliceView::Coronal, &ras);
        let (a, d) = f.index_at(ras.dims, 0.3, 0.8);
        let (u, v) = f.fraction_of(ras.dims, a, d);
        assert!((u - 0.3).abs() < 1e-12 && (v - 0.8).abs() < 1e-12);
    }
}
