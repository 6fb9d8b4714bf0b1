//! Measurements: distance and angle rulers (on slices, or between points picked in 3D) and
//! box or ellipse regions of interest on a slice with mean, SD, min, max, area and voxel count
//! in physical units. Points are level-0 continuous indices; lengths, angles and areas are
//! computed in patient millimetres, so anisotropic voxels measure right.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::orientation::{SliceFrame, SliceView};
use super::slices::SliceImage;
use strata_render::{ValueMapping, VolumeGeometry};

/// The tool the left mouse button uses in the views.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Tool {
    /// Move the crosshair (slices), orbit (3D).
    #[default]
    Navigate,
    Distance,
    Angle,
    BoxRoi,
    EllipseRoi,
}

impl Tool {
    pub const ALL: [Tool; 5] = [
        Tool::Navigate,
        Tool::Distance,
        Tool::Angle,
        Tool::BoxRoi,
        Tool::EllipseRoi,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Tool::Navigate => "Navigate",
            Tool::Distance => "Ruler",
            Tool::Angle => "Angle",
            Tool::BoxRoi => "Box ROI",
            Tool::EllipseRoi => "Ellipse ROI",
        }
    }

    pub fn hint(self) -> &'static str {
        match self {
            Tool::Navigate => "Left click / drag moves the crosshair",
            Tool::Distance => "Drag on a slice, or click two points in 3D",
            Tool::Angle => "Click three points (the second is the vertex), on a slice or in 3D",
            Tool::BoxRoi | Tool::EllipseRoi => "Drag across the region on a slice",
        }
    }
}

/// Statistics of the voxels whose centres lie inside a region, in physical units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RoiStats {
    pub mean: f64,
    pub sd: f64,
    pub min: f64,
    pub max: f64,
    pub voxels: u64,
    /// The shape's area in mm².
    pub area_mm2: f64,
    /// Octree level the values came from (0 = full resolution).
    pub level: u8,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Shape {
    Distance {
        a: [f64; 3],
        b: [f64; 3],
    },
    Angle {
        a: [f64; 3],
        vertex: [f64; 3],
        b: [f64; 3],
    },
    /// A box or an ellipse inscribed in it, drawn on `view`'s slice between two corners.
    Roi {
        view: SliceView,
        ellipse: bool,
        a: [f64; 3],
        b: [f64; 3],
        stats: Option<RoiStats>,
    },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measurement {
    pub id: u64,
    pub shape: Shape,
}

fn mm(g: &VolumeGeometry, index: [f64; 3]) -> DVec3 {
    g.patient_from_index(DVec3::from(index))
}

/// Patient distance in mm between two level-0 indices.
pub fn distance_mm(g: &VolumeGeometry, a: [f64; 3], b: [f64; 3]) -> f64 {
    (mm(g, b) - mm(g, a)).length()
}

/// The angle at `vertex` in degrees, in patient space.
pub fn angle_deg(g: &VolumeGeometry, a: [f64; 3], vertex: [f64; 3], b: [f64; 3]) -> f64 {
    let (u, v) = (mm(g, a) - mm(g, vertex), mm(g, b) - mm(g, vertex));
    let denominator = u.length() * v.length();
    if denominator <= 0.0 {
        return 0.0;
    }
    (u.dot(v) / denominator)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

impl Measurement {
    /// One line for the list and the label on screen.
    pub fn describe(&self, g: &VolumeGeometry, unit: &str) -> String {
        match &self.shape {
            Shape::Distance { a, b } => format!("Ruler {:.1} mm", distance_mm(g, *a, *b)),
            Shape::Angle { a, vertex, b } => {
                format!("Angle {:.1}°", angle_deg(g, *a, *vertex, *b))
            }
            Shape::Roi { ellipse, stats, .. } => {
                let kind = if *ellipse { "Ellipse" } else { "Box" };
                match stats {
                    Some(s) => format!(
                        "{kind} mean {:.1} SD {:.1} min {:.0} max {:.0} {unit} · {:.1} mm² · {} voxels{}",
                        s.mean,
                        s.sd,
                        s.min,
                        s.max,
                        s.area_mm2,
                        s.voxels,
                        if s.level > 0 {
                            format!(" (level {})", s.level)
                        } else {
                            String::new()
                        }
                    ),
                    None => format!("{kind} (no values yet)"),
                }
            }
        }
    }

    /// The points that define it (for drawing and for "is it on this slice").
    pub fn points(&self) -> Vec<[f64; 3]> {
        match &self.shape {
            Shape::Distance { a, b } => vec![*a, *b],
            Shape::Angle { a, vertex, b } => vec![*a, *vertex, *b],
            Shape::Roi { a, b, .. } => vec![*a, *b],
        }
    }
}

/// Statistics of a box or ellipse ROI from corners `a`, `b` (level-0 indices on the slice
/// `image` shows), over the image's voxels whose centres lie inside the shape.
pub fn roi_stats(
    image: &SliceImage,
    g: &VolumeGeometry,
    mapping: ValueMapping,
    ellipse: bool,
    a: [f64; 3],
    b: [f64; 3],
) -> Option<RoiStats> {
    let frame: SliceFrame = image.request.frame;
    let (ax, dx) = (frame.across_axis, frame.down_axis);
    let level = image.request.level;
    let scale = (1u64 << level) as f64;
    let (a0, a1) = (a[ax].min(b[ax]), a[ax].max(b[ax]));
    let (d0, d1) = (a[dx].min(b[dx]), a[dx].max(b[dx]));
    let (ca, cd) = ((a0 + a1) * 0.5, (d0 + d1) * 0.5);
    let (ra, rd) = ((a1 - a0) * 0.5, (d1 - d0) * 0.5);
    let (mut n, mut sum, mut sum2) = (0u64, 0.0f64, 0.0f64);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for y in 0..image.height {
        // Level-L voxel centre in level-0 index units.
        let d = (y as f64 + 0.5) * scale - 0.5;
        if d < d0 || d > d1 {
            continue;
        }
        for x in 0..image.width {
            let across = (x as f64 + 0.5) * scale - 0.5;
            if across < a0 || across > a1 {
                continue;
            }
            if ellipse {
                let (u, v) = ((across - ca) / ra.max(1e-12), (d - cd) / rd.max(1e-12));
                if u * u + v * v > 1.0 {
                    continue;
                }
            }
            let value = mapping.physical(image.values[y * image.width + x] as f64);
            n += 1;
            sum += value;
            sum2 += value * value;
            lo = lo.min(value);
            hi = hi.max(value);
        }
    }
    if n == 0 {
        return None;
    }
    let mean = sum / n as f64;
    // Population SD of the region's voxels (what Slicer's segment statistics report).
    let sd = (sum2 / n as f64 - mean * mean).max(0.0).sqrt();
    let box_area = (a1 - a0) * g.spacing_mm[ax] * (d1 - d0) * g.spacing_mm[dx];
    Some(RoiStats {
        mean,
        sd,
        min: lo,
        max: hi,
        voxels: n,
        area_mm2: if ellipse {
            box_area * std::f64::consts::FRAC_PI_4
        } else {
            box_area
        },
        level,
    })
}

/// A measurement being drawn.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Draft {
    pub points: Vec<[f64; 3]>,
}

/// The measurement list, the active tool and the one being drawn.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Measurements {
    pub items: Vec<Measurement>,
    pub tool: Tool,
    pub draft: Draft,
    next_id: u64,
}

impl Measurements {
    pub fn with_items(items: Vec<Measurement>) -> Self {
        let next_id = items.iter().map(|m| m.id + 1).max().unwrap_or(0);
        Measurements {
            items,
            next_id,
            ..Default::default()
        }
    }

    pub fn add(&mut self, shape: Shape) {
        self.items.push(Measurement {
            id: self.next_id,
            shape,
        });
        self.next_id += 1;
    }

    pub fn remove(&mut self, id: u64) {
        self.items.retain(|m| m.id != id);
    }

    /// A point clicked with the tool (slices: angle; 3D: distance and angle); adds the
    /// measurement once it has all its points.
    pub fn click(&mut self, point: [f64; 3]) {
        let needed = match self.tool {
            Tool::Distance => 2,
            Tool::Angle => 3,
            _ => return,
        };
        self.draft.points.push(point);
        if self.draft.points.len() >= needed {
            let p = std::mem::take(&mut self.draft.points);
            self.add(match self.tool {
                Tool::Distance => Shape::Distance { a: p[0], b: p[1] },
                _ => Shape::Angle {
                    a: p[0],
                    vertex: p[1],
                    b: p[2],
                },
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lengths_and_angles_are_in_patient_millimetres() {
        // Anisotropic: 0.5 mm across, 2 mm slices.
        let g = VolumeGeometry::axis_aligned([10, 10, 10], [0.5, 0.5, 2.0]);
        assert!((distance_mm(&g, [0.0, 0.0, 0.0], [6.0, 8.0, 0.0]) - 5.0).abs() < 1e-12);
        assert!((distance_mm(&g, [0.0, 0.0, 0.0], [0.0, 0.0, 3.0]) - 6.0).abs() < 1e-12);
        // 4 voxels across (2 mm) and 1 slice (2 mm): 45° in patient space, not 14° in index.
        let a = angle_deg(&g, [4.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        assert!((a - 90.0).abs() < 1e-9, "{a}");
        let a = angle_deg(&g, [4.0, 0.0, 0.0], [0.0, 0.0, 0.0], [4.0, 0.0, 1.0]);
        assert!((a - 45.0).abs() < 1e-9, "{a}");
    }

    #[test]
    fn clicks_complete_rulers_and_angles_and_ids_stay_unique() {
        let mut m = Measurements {
            tool: Tool::Angle,
            ..Default::default()
        };
        m.click([1.0, 0.0, 0.0]);
        m.click([0.0, 0.0, 0.0]);
        assert!(m.items.is_empty());
        m.click([0.0, 1.0, 0.0]);
        assert_eq!(m.items.len(), 1);
        m.tool = Tool::Distance;
        m.click([0.0; 3]);
        m.click([1.0; 3]);
        assert_eq!(m.items.len(), 2);
        m.remove(0);
        let restored = Measurements::with_items(m.items.clone());
        let mut restored = restored;
        restored.add(Shape::Distance {
            a: [0.0; 3],
            b: [0.0; 3],
        });
        let ids: Vec<u64> = restored.items.iter().map(|i| i.id).collect();
        assert_eq!(ids, vec![1, 2]);
    }
}
