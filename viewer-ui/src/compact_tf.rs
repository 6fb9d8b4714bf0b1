//! A transfer function in a link (`tf=`): the control points of an edited function, written
//! compactly and read back exactly (issue 39, "TF preset or a compact TF").
//!
//! `tf=V,O_V,O_…~V,R,G,B_V,R,G,B_…`: the opacity stops (value, opacity), `~`, then the colour
//! stops (value, red, green, blue), stops joined by `_`. Every number is the shortest text that
//! parses back to the same `f64` (Rust's float formatting: its decimal or exponent form,
//! whichever is shorter), so the editor's points, whatever precision a drag gave them, come
//! back bit for bit and a preset's round numbers stay short (`-1e3,0_150,0_300,0.15`).
//! Only digits and `-.e,_~` occur: nothing a browser percent-encodes or a mail client breaks.
//!
//! Bounded: at most [`MAX_TF_STOPS`] stops per list and [`MAX_TF_CHARS`] characters, checked
//! before the value is split, so a mangled or hostile link costs no more than that to reject.

use strata_render::model::transfer_function::{ColorStop, OpacityStop};
use strata_render::TransferFunction;

/// Most stops per list (opacity, colour) a link may carry: far more than a hand-edited
/// function has, few enough to keep a link below a few kilobytes.
pub const MAX_TF_STOPS: usize = 64;
/// Longest number text written: `-1.2345678901234567e-308`.
const MAX_NUMBER_CHARS: usize = 24;
/// Longest `tf=` value: [`MAX_TF_STOPS`] stops in each list with the longest numbers, so every
/// function within the stop bound can be written.
pub const MAX_TF_CHARS: usize =
    MAX_TF_STOPS * (2 * MAX_NUMBER_CHARS + 2) + MAX_TF_STOPS * (4 * MAX_NUMBER_CHARS + 4) + 1;
/// Largest magnitude of a stop's value (physical units; CT's are thousands).
pub const MAX_TF_VALUE: f64 = 1.0e12;

/// Why a `tf=` value is not a transfer function (the caller names the key).
#[derive(Debug, PartialEq)]
pub struct TfTextError(pub String);

/// The shortest text that parses back to exactly `v`.
fn number(v: f64) -> String {
    let plain = format!("{v}");
    let exponent = format!("{v:e}");
    if exponent.len() < plain.len() {
        exponent
    } else {
        plain
    }
}

/// Why `tf` cannot be written into a link (too many stops, values out of range); None: it can.
pub fn unwritable(tf: &TransferFunction) -> Option<String> {
    if tf.opacity.len() > MAX_TF_STOPS || tf.color.len() > MAX_TF_STOPS {
        return Some(format!(
            "{} opacity and {} colour stops: a link carries at most {MAX_TF_STOPS} of each",
            tf.opacity.len(),
            tf.color.len()
        ));
    }
    checked(tf).err().map(|TfTextError(why)| why)
}

/// The link text of `tf`'s stops (its name is not written).
pub fn encode(tf: &TransferFunction) -> Result<String, TfTextError> {
    if let Some(why) = unwritable(tf) {
        return Err(TfTextError(why));
    }
    let opacity: Vec<String> = tf
        .opacity
        .iter()
        .map(|s| format!("{},{}", number(s.value), number(s.opacity)))
        .collect();
    let color: Vec<String> = tf
        .color
        .iter()
        .map(|s| {
            let [r, g, b] = s.rgb.map(number);
            format!("{},{r},{g},{b}", number(s.value))
        })
        .collect();
    Ok(format!("{}~{}", opacity.join("_"), color.join("_")))
}

/// Reads [`encode`]'s text into a function named `name`.
pub fn decode(text: &str, name: &str) -> Result<TransferFunction, TfTextError> {
    if text.len() > MAX_TF_CHARS {
        return Err(TfTextError(format!(
            "{} characters, more than a link's function may have ({MAX_TF_CHARS})",
            text.len()
        )));
    }
    let (opacity_text, color_text) = text.split_once('~').ok_or_else(|| {
        TfTextError("opacity stops V,O_V,O…, `~`, colour stops V,R,G,B_… expected".into())
    })?;
    let opacity = stops::<2>(opacity_text, "opacity stop (value,opacity)")?
        .into_iter()
        .map(|[value, opacity]| OpacityStop { value, opacity })
        .collect();
    let color = stops::<4>(color_text, "colour stop (value,red,green,blue)")?
        .into_iter()
        .map(|[value, r, g, b]| ColorStop {
            value,
            rgb: [r, g, b],
        })
        .collect();
    let tf = TransferFunction {
        name: name.to_string(),
        opacity,
        color,
    };
    checked(&tf)
}

fn stops<const N: usize>(text: &str, what: &str) -> Result<Vec<[f64; N]>, TfTextError> {
    if text.is_empty() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for stop in text.split('_') {
        if out.len() == MAX_TF_STOPS {
            return Err(TfTextError(format!(
                "more than {MAX_TF_STOPS} stops in a list"
            )));
        }
        let mut numbers = [0.0; N];
        let mut parts = stop.split(',');
        for slot in &mut numbers {
            *slot = parts
                .next()
                .and_then(|p| p.parse::<f64>().ok())
                .filter(|v| v.is_finite())
                .ok_or_else(|| TfTextError(format!("`{stop}` is not a {what}")))?;
        }
        if parts.next().is_some() {
            return Err(TfTextError(format!("`{stop}` is not a {what}")));
        }
        out.push(numbers);
    }
    Ok(out)
}

/// `tf` if the renderer takes it and its values are in the link's range.
fn checked(tf: &TransferFunction) -> Result<TransferFunction, TfTextError> {
    let values = tf
        .opacity
        .iter()
        .map(|s| s.value)
        .chain(tf.color.iter().map(|s| s.value));
    if values.into_iter().any(|v| v.abs() > MAX_TF_VALUE) {
        return Err(TfTextError(format!(
            "a stop's value beyond ±{MAX_TF_VALUE:e}"
        )));
    }
    tf.validate()
        .map_err(|e| TfTextError(format!("not a transfer function: {e}")))?;
    Ok(tf.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Numbers as a drag in the editor leaves them: pixels mapped through f32 onto the range.
    fn dragged(i: usize) -> f64 {
        let fraction = ((i as f32 * 37.3 + 0.7) / 613.0).fract() as f64;
        -1024.0 + fraction * 4095.0
    }

    fn edited(stops: usize) -> TransferFunction {
        let mut values: Vec<f64> = (0..stops).map(dragged).collect();
        values.sort_by(f64::total_cmp);
        TransferFunction {
            name: "ct-bone (edited)".into(),
            opacity: values
                .iter()
                .enumerate()
                .map(|(i, &value)| OpacityStop {
                    value,
                    opacity: ((i as f32 * 0.173).fract()) as f64,
                })
                .collect(),
            color: values
                .iter()
                .enumerate()
                .map(|(i, &value)| ColorStop {
                    value,
                    rgb: [0.1, 0.37, 0.9].map(|c: f32| ((c * i as f32).fract()) as f64),
                })
                .collect(),
        }
    }

    #[test]
    fn an_edited_function_comes_back_bit_for_bit() {
        for tf in [
            edited(7),
            edited(MAX_TF_STOPS),
            TransferFunction::preset("ct-lung").expect("preset"),
        ] {
            let text = encode(&tf).expect("within the bounds");
            assert!(text.len() <= MAX_TF_CHARS, "{}", text.len());
            assert!(
                text.chars()
                    .all(|c| c.is_ascii_digit() || "-.e,_~".contains(c)),
                "{text}"
            );
            let back = decode(&text, &tf.name).expect("own text parses");
            assert_eq!(back, tf, "{text}");
            for (a, b) in back.opacity.iter().zip(&tf.opacity) {
                assert_eq!(a.value.to_bits(), b.value.to_bits());
            }
        }
        let preset = TransferFunction::preset("ct-bone").expect("preset");
        let text = encode(&preset).expect("writes");
        assert!(text.starts_with("-1e3,0_150,0_300,0.15_"), "{text}");
        // Extremes a drag cannot make still come back exactly, in their short form.
        let tiny = TransferFunction::new("x", &[(-1e-300, 1e-300), (5e11, 1.0)], &[]);
        let text = encode(&tiny).expect("writes");
        assert!(text.len() < 30, "{text}");
        assert_eq!(decode(&text, "x").expect("parses"), tiny);
    }

    #[test]
    fn bad_and_oversized_text_is_refused() {
        for bad in [
            "",
            "0,0_1,1",
            "0,0_1~",
            "0,0,0~",
            "0,x~",
            "0,NaN~",
            "0,inf~",
            "1,0_0,1~",
            "0,2~",
            "0,1~0,1,1",
            "0,1~0,1,1,1.5",
            "2e12,1~",
        ] {
            assert!(decode(bad, "x").is_err(), "{bad:?}");
        }
        let too_many = edited(MAX_TF_STOPS + 1);
        assert!(unwritable(&too_many).is_some());
        assert!(encode(&too_many).is_err());
        let many: Vec<String> = (0..=MAX_TF_STOPS).map(|i| format!("{i},0")).collect();
        let e = decode(&format!("{}~", many.join("_")), "x").expect_err("65 stops");
        assert!(e.0.contains("64"), "{e:?}");
        let long = format!("0,0{}~", "0".repeat(MAX_TF_CHARS));
        let e = decode(&long, "x").expect_err("too long");
        assert!(e.0.contains("characters"), "{e:?}");
        // Empty colour stops are a function (white everywhere), as the renderer takes it.
        assert!(decode("0,0_1,1~", "x").is_ok());
    }
}
