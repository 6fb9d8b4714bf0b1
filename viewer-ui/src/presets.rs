//! Which transfer-function presets fit a scan, and the one it opens with (issue 47: an MR
//! opened with the CT bone preset, nearly black in the page and a solid red cube in the
//! desktop). The CT presets are in HU and are offered only for CT-like data; the MR preset
//! is fitted to the scan's value range. The desktop and the page both choose the initial
//! preset with [`initial_preset`] and fit it with [`fitted_preset`], and show each preset's
//! [`Offer`] (why one is not offered, or how it was fitted). Also the scan's value
//! formatting ([`ScanValues::format_value`]): its unit, and integers where the data are.

use strata_render::{TransferFunction, ValueMapping};
use strata_storage::StoreHeader;

/// What about a scan decides its presets and how its values print.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanValues {
    /// "CT", "MR", ... or empty when the source did not say.
    pub modality: String,
    /// The physical unit ("HU"), empty when arbitrary (MR).
    pub unit: String,
    /// The lowest and highest physical value.
    pub physical_range: (f64, f64),
    /// Every physical value is an integer (integer slope and intercept over integer stored
    /// values): the readout prints no decimals.
    pub integer_values: bool,
}

impl ScanValues {
    /// The store header's modality, unit and physical range.
    pub fn of(header: &StoreHeader) -> ScanValues {
        let mapping = header.value_mapping.mapping;
        let a = mapping.physical(f64::from(header.stored_range[0]));
        let b = mapping.physical(f64::from(header.stored_range[1]));
        ScanValues {
            modality: header.modality.clone(),
            unit: header.value_mapping.unit.trim().to_string(),
            physical_range: (a.min(b), a.max(b)),
            integer_values: integer_values(&mapping),
        }
    }

    /// Whether the scan is CT (by [`looks_like_ct`]).
    pub fn is_ct(&self) -> bool {
        looks_like_ct(&self.modality, &self.unit, self.physical_range)
    }

    /// The unit values are shown in: the header's, or HU for a CT that does not say.
    pub fn display_unit(&self) -> &str {
        if self.unit.is_empty() && self.is_ct() {
            "HU"
        } else {
            &self.unit
        }
    }

    /// The label of a control over the scan's values: "iso (HU)" for CT, "iso (value)" for
    /// an MR with no unit.
    pub fn value_label(&self, what: &str) -> String {
        match self.display_unit() {
            "" => format!("{what} (value)"),
            unit => format!("{what} ({unit})"),
        }
    }

    /// A value as the readout prints it: an integer for integer data, else four significant
    /// decimals at most; with the unit when known ("76", "-1000 HU", "0.25 mm²/s").
    pub fn format_value(&self, value: f64) -> String {
        let number = format_number(value, self.integer_values);
        match self.display_unit() {
            "" => number,
            unit => format!("{number} {unit}"),
        }
    }
}

/// Whether every physical value under `mapping` is an integer (integer stored values under an
/// integer slope and intercept, e.g. 8-bit data or CT in HU).
pub fn integer_values(mapping: &ValueMapping) -> bool {
    is_integer(mapping.slope) && is_integer(mapping.intercept)
}

/// A value under the pointer as both viewers' readouts print it, with its unit when known: an
/// integer for integer data ("76", "-1000 HU"), HU without decimals, one decimal from 100 up,
/// else at most four ("0.25 mm²/s").
pub fn readout_value(value: f64, unit: &str, integer_values: bool) -> String {
    let text = if integer_values {
        format!("{} {unit}", format_number(value, true))
    } else if unit == "HU" {
        format!("{value:.0} HU")
    } else if value.abs() >= 100.0 {
        format!("{value:.1} {unit}")
    } else {
        format!("{} {unit}", format_number(value, false))
    };
    text.trim_end().to_string()
}

fn is_integer(x: f64) -> bool {
    x.is_finite() && x.fract() == 0.0
}

/// A number without needless decimals: integers as integers, others with at most 4 decimals
/// and no trailing zeros. Not finite: "—".
pub fn format_number(value: f64, integer_values: bool) -> String {
    if !value.is_finite() {
        return "—".into();
    }
    if integer_values || is_integer(value) {
        return format!("{}", value.round() as i64);
    }
    let text = format!("{value:.4}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    if text == "-0" { "0" } else { text }.to_string()
}

/// Whether a scan is CT: its modality or unit says so, or an untagged scan whose values span
/// air (about −1000) to bone (a NRRD or NIfTI in HU often carries neither).
pub fn looks_like_ct(modality: &str, unit: &str, physical_range: (f64, f64)) -> bool {
    if modality.eq_ignore_ascii_case("CT") || unit.eq_ignore_ascii_case("HU") {
        return true;
    }
    let untagged = modality.trim().is_empty() || modality.eq_ignore_ascii_case("OT");
    let (lo, hi) = physical_range;
    untagged && (-1100.0..=-700.0).contains(&lo) && hi >= 300.0
}

/// Whether a preset is offered for a scan, and why (shown on hover).
#[derive(Clone, Debug, PartialEq)]
pub enum Offer {
    /// The preset is meant for this kind of scan, as it is.
    Fits,
    /// Offered, fitted to the scan's values (the reason says how).
    Fitted(String),
    /// Not offered (the reason says why).
    NotOffered(String),
}

impl Offer {
    pub fn is_offered(&self) -> bool {
        !matches!(self, Offer::NotOffered(_))
    }

    /// The reason to show, if any.
    pub fn reason(&self) -> Option<&str> {
        match self {
            Offer::Fits => None,
            Offer::Fitted(r) | Offer::NotOffered(r) => Some(r),
        }
    }
}

/// Whether `preset` ([`TransferFunction::PRESETS`]) is offered for `scan`, and why.
pub fn offer(preset: &str, scan: &ScanValues) -> Offer {
    let (lo, hi) = scan.physical_range;
    let range = format!(
        "{} to {}",
        format_number(lo, scan.integer_values),
        scan.format_value(hi)
    );
    if preset.starts_with("ct-") {
        if scan.is_ct() {
            Offer::Fits
        } else {
            let what = match scan.modality.trim() {
                "" => "this scan is not tagged CT".to_string(),
                m => format!("this scan is {m}"),
            };
            Offer::NotOffered(format!(
                "A CT preset, in HU; {what} and its values run from {range}, so it would \
                 paint nothing or a solid block."
            ))
        }
    } else if preset.starts_with("mr") {
        Offer::Fitted(format!(
            "Fitted to this scan's values ({range}): the preset's 0–1000 is stretched \
             onto them."
        ))
    } else {
        Offer::Fits
    }
}

/// The preset a scan opens with when nothing asked for one: CT bone for CT, else the MR
/// preset fitted to the scan's values. The desktop and the page both call this.
pub fn initial_preset(scan: &ScanValues) -> &'static str {
    if scan.is_ct() {
        "ct-bone"
    } else {
        "mr-default"
    }
}

/// Whether the preset the user last chose (kept in the preferences) is kept for this scan
/// when nothing asked for one: a known preset meant for its kind (CT presets for CT, the MR
/// preset for the rest); otherwise the scan opens with [`initial_preset`].
pub fn keeps_preset(preset: &str, scan: &ScanValues) -> bool {
    TransferFunction::PRESETS.contains(&preset) && preset.starts_with("ct-") == scan.is_ct()
}

/// The preset's function fitted to a scan whose physical range is `physical_range`: the MR
/// preset assumes intensities near 0..1000 and is stretched onto the range; the CT presets
/// are in HU and stay as they are. An unknown name: a grey ramp over [0, 1].
pub fn fitted_preset(name: &str, physical_range: (f64, f64)) -> TransferFunction {
    let mut tf = TransferFunction::preset(name).unwrap_or_else(|| {
        TransferFunction::new(name, &[(0.0, 0.0), (1.0, 1.0)], &[(0.0, [1.0; 3])])
    });
    if name.starts_with("mr") {
        let (lo, hi) = physical_range;
        let scale = (hi - lo).max(1e-6) / 1000.0;
        for p in &mut tf.opacity {
            p.value = lo + p.value * scale;
        }
        for c in &mut tf.color {
            c.value = lo + c.value * scale;
        }
    }
    tf
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ct() -> ScanValues {
        ScanValues {
            modality: "CT".into(),
            unit: "HU".into(),
            physical_range: (-1024.0, 3071.0),
            integer_values: true,
        }
    }

    fn mr() -> ScanValues {
        ScanValues {
            modality: "MR".into(),
            unit: String::new(),
            physical_range: (0.0, 255.0),
            integer_values: true,
        }
    }

    #[test]
    fn a_ct_opens_with_bone_and_an_mr_with_the_fitted_mr_preset() {
        assert_eq!(initial_preset(&ct()), "ct-bone");
        assert_eq!(initial_preset(&mr()), "mr-default");
        // An untagged scan in HU (a NRRD) is CT; an untagged 8-bit one is not.
        let untagged_hu = ScanValues {
            modality: String::new(),
            unit: String::new(),
            physical_range: (-1000.0, 1900.0),
            integer_values: true,
        };
        assert_eq!(initial_preset(&untagged_hu), "ct-bone");
        let untagged_8_bit = ScanValues {
            modality: String::new(),
            ..mr()
        };
        assert_eq!(initial_preset(&untagged_8_bit), "mr-default");
        let fitted = fitted_preset("mr-default", mr().physical_range);
        let last = fitted.opacity.last().expect("stops").value;
        assert_eq!(last, 255.0, "the MR preset ends at the scan's top");
    }

    #[test]
    fn ct_presets_are_not_offered_for_an_mr_and_say_why() {
        for name in TransferFunction::PRESETS {
            assert!(offer(name, &ct()).is_offered(), "{name} on CT");
        }
        let bone = offer("ct-bone", &mr());
        assert!(!bone.is_offered());
        let why = bone.reason().expect("a reason");
        assert!(
            why.contains("HU") && why.contains("MR") && why.contains("0 to 255"),
            "{why}"
        );
        assert!(matches!(offer("mr-default", &mr()), Offer::Fitted(_)));
        // A saved CT preset is dropped on an MR, the MR preset on a CT.
        assert!(!keeps_preset("ct-soft-tissue", &mr()));
        assert!(keeps_preset("ct-soft-tissue", &ct()));
        assert!(keeps_preset("mr-default", &mr()));
        assert!(!keeps_preset("mr-default", &ct()));
        assert!(!keeps_preset("nope", &ct()));
    }

    #[test]
    fn values_print_in_the_scans_unit_and_integers_for_integer_data() {
        assert_eq!(mr().format_value(76.0), "76");
        assert_eq!(ct().format_value(-1000.0), "-1000 HU");
        assert_eq!(ct().value_label("iso"), "iso (HU)");
        assert_eq!(mr().value_label("iso"), "iso (value)");
        let float = ScanValues {
            unit: "mm²/s".into(),
            integer_values: false,
            ..mr()
        };
        assert_eq!(float.format_value(0.25), "0.25 mm²/s");
        assert_eq!(float.format_value(1.0 / 3.0), "0.3333 mm²/s");
        assert_eq!(format_number(f64::NAN, false), "—");
        assert_eq!(format_number(-0.00001, false), "0");
    }

    /// The page and the desktop choose the initial preset with this module's one function,
    /// and fit it with [`fitted_preset`] (issue 47: the page opened an MR with CT bone).
    #[test]
    fn the_page_and_the_desktop_call_the_same_choice() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let read = |path: &str| {
            std::fs::read_to_string(root.join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
        };
        let page = read("web/src/browser.rs");
        let desktop = read("viewer/src/app.rs");
        for (name, text) in [("page", &page), ("desktop", &desktop)] {
            assert!(
                text.contains("presets::initial_preset(&scan)"),
                "the {name} chooses"
            );
            assert!(
                text.contains("ScanValues::of("),
                "the {name} reads the header"
            );
        }
        assert!(read("web/src/side_panel.rs").contains("presets::fitted_preset("));
        assert!(read("viewer/src/scene.rs").contains("presets::fitted_preset("));
    }
}
