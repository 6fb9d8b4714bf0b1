//! Piecewise-linear transfer function over physical values (HU for CT), its presets, JSON
//! form, the sampled table the GPU reads, and an opacity prefix sum so the loader can ask
//! "is anything in [min, max] visible?" in O(1).

use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::error::RenderError;

/// Entries in the GPU table. 4096 over the used physical range keeps table spacing well below
/// one 12-bit CT unit step; the table is linearly interpolated, so knots are honoured closely.
pub const TABLE_ENTRIES: usize = 4096;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OpacityStop {
    pub value: f64,
    pub opacity: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColorStop {
    pub value: f64,
    pub rgb: [f64; 3],
}

/// Opacity is per finest-voxel-edge of travel (the step the opacity correction refers to).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransferFunction {
    pub name: String,
    pub opacity: Vec<OpacityStop>,
    pub color: Vec<ColorStop>,
}

/// Piecewise-linear interpolation over sorted stops, constant beyond the ends.
fn lerp_stops<T: Copy>(
    n: usize,
    key: impl Fn(usize) -> (f64, T),
    v: f64,
    mix: impl Fn(T, T, f64) -> T,
    empty: T,
) -> T {
    if n == 0 {
        return empty;
    }
    let first = key(0);
    if n == 1 || v <= first.0 {
        return first.1;
    }
    let last = key(n - 1);
    if v >= last.0 {
        return last.1;
    }
    // Stops are sorted (validated); a linear scan is fine for tens of stops.
    for i in 1..n {
        let (b, a) = (key(i), key(i - 1));
        if v <= b.0 {
            let span = b.0 - a.0;
            let t = if span > 0.0 { (v - a.0) / span } else { 1.0 };
            return mix(a.1, b.1, t);
        }
    }
    last.1
}

impl TransferFunction {
    pub fn new(name: &str, opacity: &[(f64, f64)], color: &[(f64, [f64; 3])]) -> Self {
        TransferFunction {
            name: name.to_string(),
            opacity: opacity
                .iter()
                .map(|&(value, opacity)| OpacityStop { value, opacity })
                .collect(),
            color: color
                .iter()
                .map(|&(value, rgb)| ColorStop { value, rgb })
                .collect(),
        }
    }

    pub fn validate(&self) -> Result<(), RenderError> {
        if self.opacity.is_empty() {
            return Err(RenderError::InvalidTransferFunction(format!(
                "'{}' has no opacity stops",
                self.name
            )));
        }
        let sorted = |vals: Vec<f64>| {
            vals.windows(2).all(|w| w[0] <= w[1]) && vals.iter().all(|v| v.is_finite())
        };
        if !sorted(self.opacity.iter().map(|s| s.value).collect())
            || !sorted(self.color.iter().map(|s| s.value).collect())
        {
            return Err(RenderError::InvalidTransferFunction(format!(
                "'{}': stop values must be finite and ascending",
                self.name
            )));
        }
        if self
            .opacity
            .iter()
            .any(|s| !(0.0..=1.0).contains(&s.opacity))
        {
            return Err(RenderError::InvalidTransferFunction(format!(
                "'{}': opacity outside [0,1]",
                self.name
            )));
        }
        if self
            .color
            .iter()
            .any(|s| s.rgb.iter().any(|c| !(0.0..=1.0).contains(c)))
        {
            return Err(RenderError::InvalidTransferFunction(format!(
                "'{}': colour outside [0,1]",
                self.name
            )));
        }
        Ok(())
    }

    pub fn opacity_at(&self, value: f64) -> f64 {
        lerp_stops(
            self.opacity.len(),
            |i| (self.opacity[i].value, self.opacity[i].opacity),
            value,
            |a, b, t| a + (b - a) * t,
            0.0,
        )
    }

    pub fn color_at(&self, value: f64) -> [f64; 3] {
        lerp_stops(
            self.color.len(),
            |i| (self.color[i].value, self.color[i].rgb),
            value,
            |a, b, t| [0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * t),
            [1.0; 3],
        )
    }

    /// Largest opacity over [lo, hi]: piecewise linear, so the max is at an end or a stop.
    pub fn max_opacity_in(&self, lo: f64, hi: f64) -> f64 {
        let mut m = self.opacity_at(lo).max(self.opacity_at(hi));
        for s in &self.opacity {
            if s.value > lo && s.value < hi {
                m = m.max(s.opacity);
            }
        }
        m
    }

    pub fn to_json(&self) -> Result<String, RenderError> {
        Ok(serde_json::to_string_pretty(self)?)
    }

    pub fn from_json(text: &str) -> Result<Self, RenderError> {
        let tf: TransferFunction = serde_json::from_str(text)?;
        tf.validate()?;
        Ok(tf)
    }

    pub fn load(path: &Path) -> Result<Self, RenderError> {
        let text = std::fs::read_to_string(path).map_err(|source| RenderError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_json(&text)
            .map_err(|e| RenderError::InvalidTransferFunction(format!("{}: {e}", path.display())))
    }

    pub fn save(&self, path: &Path) -> Result<(), RenderError> {
        let text = self.to_json()?;
        std::fs::write(path, text).map_err(|source| RenderError::Io {
            path: path.display().to_string(),
            source,
        })
    }

    /// Names accepted by [`TransferFunction::preset`].
    pub const PRESETS: [&'static str; 5] = [
        "ct-bone",
        "ct-soft-tissue",
        "ct-lung",
        "ct-vessels",
        "mr-default",
    ];

    /// Presets in the spirit of 3D Slicer's volume-rendering presets. CT values are HU; the MR
    /// preset assumes intensities normalised to roughly [0, 1000].
    pub fn preset(name: &str) -> Option<Self> {
        let tf = match name {
            "ct-bone" => Self::new(
                "ct-bone",
                &[
                    (-1000.0, 0.0),
                    (150.0, 0.0),
                    (300.0, 0.15),
                    (700.0, 0.6),
                    (3000.0, 0.8),
                ],
                &[
                    (-1000.0, [0.0, 0.0, 0.0]),
                    (150.0, [0.55, 0.25, 0.15]),
                    (300.0, [0.9, 0.82, 0.65]),
                    (3000.0, [1.0, 1.0, 0.95]),
                ],
            ),
            "ct-soft-tissue" => Self::new(
                "ct-soft-tissue",
                &[
                    (-1000.0, 0.0),
                    (-200.0, 0.0),
                    (-50.0, 0.02),
                    (60.0, 0.08),
                    (300.0, 0.3),
                    (3000.0, 0.5),
                ],
                &[
                    (-1000.0, [0.0, 0.0, 0.0]),
                    (-100.0, [0.7, 0.45, 0.35]),
                    (60.0, [0.85, 0.35, 0.3]),
                    (300.0, [1.0, 0.95, 0.85]),
                ],
            ),
            "ct-lung" => Self::new(
                "ct-lung",
                &[
                    (-1000.0, 0.0),
                    (-900.0, 0.0),
                    (-750.0, 0.06),
                    (-500.0, 0.1),
                    (-300.0, 0.0),
                    (3000.0, 0.0),
                ],
                &[
                    (-1000.0, [0.3, 0.5, 0.8]),
                    (-750.0, [0.75, 0.85, 1.0]),
                    (-300.0, [1.0, 1.0, 1.0]),
                ],
            ),
            "ct-vessels" => Self::new(
                "ct-vessels",
                &[
                    (-1000.0, 0.0),
                    (120.0, 0.0),
                    (200.0, 0.3),
                    (400.0, 0.7),
                    (3000.0, 0.8),
                ],
                &[
                    (-1000.0, [0.0, 0.0, 0.0]),
                    (120.0, [0.6, 0.05, 0.05]),
                    (250.0, [0.95, 0.3, 0.25]),
                    (600.0, [1.0, 0.95, 0.9]),
                ],
            ),
            "mr-default" => Self::new(
                "mr-default",
                &[(0.0, 0.0), (100.0, 0.0), (400.0, 0.1), (1000.0, 0.4)],
                &[
                    (0.0, [0.0, 0.0, 0.0]),
                    (300.0, [0.8, 0.7, 0.6]),
                    (1000.0, [1.0, 1.0, 1.0]),
                ],
            ),
            _ => return None,
        };
        Some(tf)
    }

    /// Samples the function over the physical range [lo, hi] (normally the volume's range).
    pub fn table(&self, lo: f64, hi: f64) -> TransferFunctionTable {
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let n = TABLE_ENTRIES;
        let spacing = (hi - lo) / (n - 1) as f64;
        let value_at = |i: usize| lo + spacing * i as f64;
        let rgba: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                let v = value_at(i);
                let c = self.color_at(v);
                [
                    c[0] as f32,
                    c[1] as f32,
                    c[2] as f32,
                    self.opacity_at(v) as f32,
                ]
            })
            .collect();
        // Bin i spans table entries i and i+1; its max opacity is conservative for any value
        // in that span, so the emptiness test never hides a visible narrow peak.
        let mut opacity_prefix = Vec::with_capacity(n + 1);
        opacity_prefix.push(0.0);
        let mut acc = 0.0;
        for i in 0..n {
            let bin_max = if i + 1 < n {
                self.max_opacity_in(value_at(i), value_at(i + 1))
            } else {
                self.opacity_at(value_at(i))
            };
            acc += bin_max;
            opacity_prefix.push(acc);
        }
        TransferFunctionTable {
            lo,
            hi,
            rgba,
            opacity_prefix,
            source: self.clone(),
        }
    }
}

/// The transfer function sampled at `TABLE_ENTRIES` evenly spaced physical values in [lo, hi].
#[derive(Clone, Debug)]
pub struct TransferFunctionTable {
    pub lo: f64,
    pub hi: f64,
    /// RGB colour (not premultiplied) and opacity per entry.
    pub rgba: Vec<[f32; 4]>,
    /// opacity_prefix[i] = Σ_{j<i} max opacity in bin j (bin j = entries j..j+1).
    pub opacity_prefix: Vec<f64>,
    /// The function the table was sampled from: exact colours where the table range clamps
    /// (e.g. an iso value outside the data range).
    pub source: TransferFunction,
}

impl TransferFunctionTable {
    fn position(&self, value: f64) -> f64 {
        ((value - self.lo) / (self.hi - self.lo) * (self.rgba.len() - 1) as f64)
            .clamp(0.0, (self.rgba.len() - 1) as f64)
    }

    /// True if no value in [min, max] (physical) can get non-zero opacity. O(1).
    pub fn is_transparent(&self, min: f64, max: f64) -> bool {
        let (min, max) = if min <= max { (min, max) } else { (max, min) };
        let n = self.rgba.len();
        let first_bin = (self.position(min).floor() as usize).min(n - 1);
        // The bin holding max ends one entry later; include it.
        let last_bin = (self.position(max).floor() as usize).min(n - 1);
        let sum = self.opacity_prefix[last_bin + 1] - self.opacity_prefix[first_bin];
        // Values below lo / above hi clamp to the end entries, which the bins already cover.
        sum <= 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_round_trip_json() {
        for name in TransferFunction::PRESETS {
            let tf = TransferFunction::preset(name).unwrap();
            tf.validate().unwrap();
            let back = TransferFunction::from_json(&tf.to_json().unwrap()).unwrap();
            assert_eq!(tf, back);
        }
    }

    #[test]
    fn bad_json_is_an_error_not_a_panic() {
        assert!(TransferFunction::from_json("{").is_err());
        let descending = r#"{"name":"x","opacity":[{"value":5,"opacity":0},{"value":1,"opacity":1}],"color":[]}"#;
        assert!(TransferFunction::from_json(descending).is_err());
    }

    #[test]
    fn transparency_query_matches_brute_force() {
        let tf = TransferFunction::preset("ct-bone").unwrap();
        let table = tf.table(-1024.0, 3071.0);
        assert!(table.is_transparent(-1000.0, 100.0));
        assert!(!table.is_transparent(-1000.0, 200.0));
        assert!(!table.is_transparent(400.0, 400.0));
        // Narrow spike between two table entries must still count as visible.
        let spike = TransferFunction::new(
            "spike",
            &[(0.0, 0.0), (100.0, 0.0), (100.01, 1.0), (100.02, 0.0)],
            &[],
        );
        let t = spike.table(0.0, 4095.0);
        assert!(!t.is_transparent(99.0, 101.0));
        assert!(t.is_transparent(0.0, 99.0));
    }
}
