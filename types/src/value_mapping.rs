//! What the stored integers mean physically.

use serde::{Deserialize, Serialize};

/// physical = slope · stored + intercept (e.g. Hounsfield units for CT).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueMapping {
    pub slope: f64,
    pub intercept: f64,
}

impl Default for ValueMapping {
    fn default() -> Self {
        ValueMapping {
            slope: 1.0,
            intercept: 0.0,
        }
    }
}

impl ValueMapping {
    pub fn physical(&self, stored: f64) -> f64 {
        self.slope * stored + self.intercept
    }
}
