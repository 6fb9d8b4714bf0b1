//! A deterministic CT-like phantom in Hounsfield units, generated slice by slice.
//!
//! Anatomy in normalised coordinates u ∈ [−0.5, 0.5] per axis (x left→right of the image,
//! y anterior→posterior, z inferior→superior in the slice index): air outside an elliptic body,
//! a fat layer under the skin, soft tissue, two lungs with fine vessels, a contrast-filled aorta
//! (~300 HU) and branching vessels, a spine of cortical shell (1200 HU) around trabecular bone,
//! ribs, a one-voxel-wide calcified wire and a one-voxel-thin plate (thin-structure tests), and
//! mild deterministic noise (±10 HU). Nothing depends on the slice order or a random generator,
//! so any size up to 2048³ streams to disk and every run produces the same voxels.

use std::io::Write;
use std::path::Path;

use rayon::prelude::*;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::import::{import_slices, ImportOptions, ImportReport, SliceProducer, VolumeMeta};
use crate::quantize::StoredScalar;
use crate::source::{SampleType, WindowPreset};
use crate::store::{ValueMapping, ValueMappingWithUnit};

/// Stored value = HU + 1024 (the usual CT offset), so −1024 HU is stored as 0.
pub const PHANTOM_INTERCEPT: f64 = -1024.0;

/// Stored value = HU + 1024 in HU: the value mapping of every synthetic CT (this phantom and
/// the sparse one).
pub fn phantom_value_mapping() -> ValueMappingWithUnit {
    ValueMappingWithUnit {
        mapping: ValueMapping {
            slope: 1.0,
            intercept: PHANTOM_INTERCEPT,
        },
        unit: "HU".into(),
    }
}

pub struct Phantom {
    pub size: [u64; 3],
}

impl Phantom {
    pub fn cube(n: u64) -> Self {
        Phantom { size: [n, n, n] }
    }

    pub fn geometry(&self) -> VolumeGeometry {
        // A 400 mm field of view, like an abdominal CT, whatever the voxel count.
        let spacing = 400.0 / self.size[0].max(self.size[1]) as f64;
        // An absurd size saturates and is refused by the importer's geometry check.
        let dims = self.size.map(|d| u32::try_from(d).unwrap_or(u32::MAX));
        let mut g = VolumeGeometry::axis_aligned(dims, [spacing, spacing, spacing]);
        g.origin_lps_mm = [
            -0.5 * spacing * (self.size[0] - 1) as f64,
            -0.5 * spacing * (self.size[1] - 1) as f64,
            -0.5 * spacing * (self.size[2] - 1) as f64,
        ];
        g
    }

    pub fn meta(&self) -> VolumeMeta {
        VolumeMeta {
            geometry: self.geometry(),
            stored: StoredScalar::U16,
            value_mapping: phantom_value_mapping(),
            source_sample_type: SampleType::I16,
            quantization_error: 0.0,
            non_finite_samples: 0,
            modality: "CT".into(),
            windows: vec![
                WindowPreset {
                    name: "Soft tissue".into(),
                    center: 40.0,
                    width: 400.0,
                },
                WindowPreset {
                    name: "Bone".into(),
                    center: 400.0,
                    width: 1800.0,
                },
                WindowPreset {
                    name: "Lung".into(),
                    center: -600.0,
                    width: 1500.0,
                },
            ],
            description: format!(
                "Strata synthetic CT phantom {}x{}x{}",
                self.size[0], self.size[1], self.size[2]
            ),
            inputs: vec![],
            source_format: "phantom".into(),
            labels: Vec::new(),
        }
    }

    /// Hounsfield value of voxel (i, j, k).
    pub fn hu(&self, i: u64, j: u64, k: u64) -> i16 {
        let [nx, ny, nz] = self.size;
        let u = (i as f64 + 0.5) / nx as f64 - 0.5;
        let v = (j as f64 + 0.5) / ny as f64 - 0.5;
        let w = (k as f64 + 0.5) / nz as f64 - 0.5;
        let mut hu = anatomy(u, v, w);
        // Thin structures at exact voxel indices, one voxel wide whatever the size.
        if i == nx / 2 + nx / 7 && j == ny / 2 - ny / 9 && hu > -900.0 {
            hu = 1000.0; // calcified wire along z
        }
        if k == nz / 3 && inside_ellipse(u, v + 0.02, 0.12, 0.08) {
            hu = 250.0; // one-voxel-thin plate
        }
        if hu > -990.0 {
            hu += noise(i, j, k);
        }
        hu.round().clamp(-1024.0, 3071.0) as i16
    }

    /// Stored values of slice `k` (HU + 1024).
    pub fn stored_slice(&self, k: u64, out: &mut [u16]) {
        let nx = self.size[0] as usize;
        out.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
            for (i, v) in row.iter_mut().enumerate() {
                *v = (self.hu(i as u64, j as u64, k) as i32 - PHANTOM_INTERCEPT as i32) as u16;
            }
        });
    }

    /// Writes the phantom as a store.
    pub fn write_store(&self, path: &Path, options: &ImportOptions) -> Result<ImportReport> {
        import_slices(self, self.meta(), path, options)
    }

    /// [`Phantom::write_store`] in store format `format` (2: sled, as earlier builds wrote).
    #[doc(hidden)]
    pub fn write_store_as_format(
        &self,
        path: &Path,
        options: &ImportOptions,
        format: u32,
    ) -> Result<ImportReport> {
        crate::import::import_slices_as(self, self.meta(), path, options, Some(format))
    }

    /// Writes the phantom as an NRRD file (int16 HU, raw little-endian, attached header),
    /// streaming slice by slice.
    pub fn write_nrrd(&self, path: &Path, progress: Option<&dyn Fn(u64, u64)>) -> Result<()> {
        let g = self.geometry();
        let file = std::fs::File::create(path).map_err(|e| StorageError::io(path, e))?;
        let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
        let io = |e| StorageError::io(path, e);
        write!(
            out,
            "NRRD0004\n# Strata synthetic CT phantom (Hounsfield units)\ntype: int16\ndimension: 3\nspace: left-posterior-superior\nsizes: {} {} {}\nspace directions: ({},0,0) (0,{},0) (0,0,{})\nkinds: domain domain domain\nendian: little\nencoding: raw\nspace origin: ({},{},{})\n\n",
            self.size[0], self.size[1], self.size[2],
            g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2],
            g.origin_lps_mm[0], g.origin_lps_mm[1], g.origin_lps_mm[2]
        )
        .map_err(io)?;
        let mut slice = vec![0u16; (self.size[0] * self.size[1]) as usize];
        let mut bytes = Vec::with_capacity(slice.len() * 2);
        for k in 0..self.size[2] {
            self.stored_slice(k, &mut slice);
            bytes.clear();
            for &s in &slice {
                bytes.extend_from_slice(
                    &((s as i32 + PHANTOM_INTERCEPT as i32) as i16).to_le_bytes(),
                );
            }
            out.write_all(&bytes).map_err(io)?;
            if let Some(p) = progress {
                p(k + 1, self.size[2]);
            }
        }
        out.flush().map_err(io)?;
        Ok(())
    }
}

impl SliceProducer for Phantom {
    fn dims(&self) -> [u64; 3] {
        self.size
    }
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> Result<()> {
        Phantom::stored_slice(self, k, out);
        Ok(())
    }
    fn source_bytes_per_slice(&self) -> u64 {
        self.size[0] * self.size[1] * 2
    }
}

fn inside_ellipse(x: f64, y: f64, rx: f64, ry: f64) -> bool {
    (x / rx).powi(2) + (y / ry).powi(2) <= 1.0
}

/// The phantom's anatomy in HU, before thin structures and noise.
fn anatomy(x: f64, y: f64, z: f64) -> f64 {
    // Body tapers slightly towards the ends, like a trunk.
    let taper = 1.0 - 0.25 * z * z;
    let (bx, by) = (0.44 * taper, 0.32 * taper);
    if !inside_ellipse(x, y, bx, by) {
        return -1000.0;
    }
    // Spine: vertebral bodies behind the centre, with discs between them.
    let (sx, sy) = (x, y - 0.17);
    let r_spine = (sx * sx + sy * sy).sqrt();
    let disc = ((z * 12.0).fract().abs() - 0.5).abs() < 0.06;
    if r_spine < 0.055 {
        return if disc {
            80.0
        } else if r_spine > 0.045 {
            1200.0
        } else {
            250.0
        };
    }
    // Ribs: thin arcs near the body wall at regular heights.
    let rib_phase = ((z + 0.5) * 10.0).fract();
    let wall = (x / (bx * 0.9)).powi(2) + (y / (by * 0.9)).powi(2);
    if (rib_phase - 0.5).abs() < 0.06 && (wall - 1.0).abs() < 0.05 && y > -0.15 {
        return 900.0;
    }
    // Subcutaneous fat between the skin and the inner wall.
    if wall > 1.0 {
        return -100.0;
    }
    // Aorta in front of the spine, filled with contrast.
    let (ax, ay) = (x + 0.03, y - 0.08);
    if (ax * ax + ay * ay).sqrt() < 0.03 {
        return 300.0;
    }
    // Lungs in the upper half of the trunk, with a branching vessel tree.
    for side in [-1.0, 1.0] {
        let (lx, ly, lz) = (x - side * 0.19, y + 0.02, z - 0.12);
        if (lx / 0.14).powi(2) + (ly / 0.2).powi(2) + (lz / 0.33).powi(2) <= 1.0 {
            let vessel =
                ((lx * 60.0).sin() * (lz * 45.0).cos()).abs() < 0.08 && (ly * 50.0).sin() > 0.6;
            return if vessel { 200.0 } else { -850.0 };
        }
    }
    // Liver-like organ and kidneys slightly denser than muscle.
    if (x + 0.15).powi(2) / 0.03 + (y + 0.05).powi(2) / 0.02 + (z + 0.2).powi(2) / 0.04 <= 1.0 {
        return 60.0;
    }
    for side in [-1.0, 1.0] {
        if inside_ellipse(x - side * 0.12, y - 0.13, 0.04, 0.05) && (z + 0.15).abs() < 0.1 {
            return 150.0;
        }
    }
    40.0
}

/// Deterministic ±10 HU noise from a hash of the voxel index.
fn noise(i: u64, j: u64, k: u64) -> f64 {
    let mut h = i.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ j.wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ k.wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 32;
    (h % 21) as f64 - 10.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phantom_has_the_promised_tissues() {
        let p = Phantom::cube(128);
        let mut seen = std::collections::BTreeSet::new();
        for k in (0..128).step_by(3) {
            for j in (0..128).step_by(2) {
                for i in 0..128 {
                    let hu = p.hu(i, j, k) as i32;
                    let class = match hu {
                        -1024..=-950 => "air",
                        -900..=-700 => "lung",
                        -120..=-80 => "fat",
                        20..=70 => "soft",
                        280..=320 => "contrast",
                        700..=1500 => "bone",
                        _ => "other",
                    };
                    seen.insert(class);
                }
            }
        }
        for class in ["air", "lung", "fat", "soft", "contrast", "bone"] {
            assert!(seen.contains(class), "phantom lacks {class}: {seen:?}");
        }
        // Deterministic.
        assert_eq!(p.hu(40, 50, 60), Phantom::cube(128).hu(40, 50, 60));
    }
}
