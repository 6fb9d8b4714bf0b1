//! Segments: what each label value means (name, colour, visibility, lock, DICOM category).

use serde::{Deserialize, Serialize};

pub use strata_types::{Code, SegmentCategory};

use crate::{Label, SegmentError, MAX_SEGMENTS};

/// One segment of a label layer.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Segment {
    /// The label value its voxels hold (1..=65 535).
    pub value: Label,
    pub name: String,
    /// sRGB display colour.
    pub rgb: [u8; 3],
    pub visible: bool,
    /// A locked segment's voxels are never painted over or erased by a tool.
    pub locked: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub category: Option<SegmentCategory>,
}

/// The segments of a layer, ordered by label value.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SegmentTable {
    segments: Vec<Segment>,
}

impl SegmentTable {
    pub fn new() -> Self {
        SegmentTable::default()
    }

    pub fn iter(&self) -> impl Iterator<Item = &Segment> {
        self.segments.iter()
    }

    pub fn len(&self) -> usize {
        self.segments.len()
    }

    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    pub fn get(&self, value: Label) -> Option<&Segment> {
        self.segments
            .binary_search_by_key(&value, |s| s.value)
            .ok()
            .map(|i| &self.segments[i])
    }

    pub fn get_mut(&mut self, value: Label) -> Option<&mut Segment> {
        self.segments
            .binary_search_by_key(&value, |s| s.value)
            .ok()
            .map(|i| &mut self.segments[i])
    }

    /// Whether tools must leave voxels of this label alone. Background is never locked.
    pub fn is_locked(&self, value: Label) -> bool {
        value != 0 && self.get(value).is_some_and(|s| s.locked)
    }

    /// Adds a segment with the lowest free label value and a palette colour.
    pub fn add(&mut self, name: impl Into<String>) -> Result<Label, SegmentError> {
        if self.segments.len() >= MAX_SEGMENTS {
            return Err(SegmentError::TooManySegments {
                limit: MAX_SEGMENTS,
                requested: self.segments.len() + 1,
            });
        }
        // Values are sorted: the first gap (or the end) is the lowest free one.
        let mut value: Label = 1;
        for s in &self.segments {
            if s.value != value {
                break;
            }
            value += 1;
        }
        let rgb = label_colour(i64::from(value));
        self.insert(Segment {
            value,
            name: name.into(),
            rgb,
            visible: true,
            locked: false,
            category: None,
        })?;
        Ok(value)
    }

    /// Inserts (or replaces) the segment with `segment.value`.
    pub fn insert(&mut self, segment: Segment) -> Result<(), SegmentError> {
        if segment.value == 0 {
            return Err(SegmentError::NoSuchSegment(0));
        }
        match self
            .segments
            .binary_search_by_key(&segment.value, |s| s.value)
        {
            Ok(i) => self.segments[i] = segment,
            Err(i) => self.segments.insert(i, segment),
        }
        Ok(())
    }

    /// Removes a segment's entry (its voxels are the caller's to clear, as one edit).
    pub fn remove(&mut self, value: Label) -> Option<Segment> {
        let i = self
            .segments
            .binary_search_by_key(&value, |s| s.value)
            .ok()?;
        Some(self.segments.remove(i))
    }
}

/// A label's colour where a file or the user gives none, the one scheme of every view and
/// export: a fixed table for the first labels (distinct, saturated, as segmentation tools use),
/// then hues spaced by the golden angle so neighbouring numbers differ.
pub fn label_colour(label: i64) -> [u8; 3] {
    const TABLE: [[u8; 3]; 12] = [
        [230, 25, 75],
        [60, 180, 75],
        [255, 225, 25],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
        [250, 190, 212],
        [0, 128, 128],
        [170, 110, 40],
    ];
    if (1..=TABLE.len() as i64).contains(&label) {
        return TABLE[(label - 1) as usize];
    }
    let hue = (label as f64 * 137.507_764).rem_euclid(360.0) / 60.0;
    let x = 1.0 - (hue % 2.0 - 1.0).abs();
    let (r, g, b) = match hue as u32 {
        0 => (1.0, x, 0.0),
        1 => (x, 1.0, 0.0),
        2 => (0.0, 1.0, x),
        3 => (0.0, x, 1.0),
        4 => (x, 0.0, 1.0),
        _ => (1.0, 0.0, x),
    };
    [r, g, b].map(|c: f64| (40.0 + 215.0 * c).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_segments_take_the_lowest_free_value() {
        let mut t = SegmentTable::new();
        assert_eq!(t.add("a").unwrap(), 1);
        assert_eq!(t.add("b").unwrap(), 2);
        assert_eq!(t.add("c").unwrap(), 3);
        t.remove(2);
        assert_eq!(t.add("d").unwrap(), 2);
        assert_eq!(t.get(2).unwrap().name, "d");
        t.get_mut(3).unwrap().locked = true;
        assert!(t.is_locked(3));
        assert!(!t.is_locked(0));
    }
}
