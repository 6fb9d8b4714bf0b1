use std::path::Path;

use anyhow::Result;

use strata_viewer::volume_location::{open, Opened};

/// Anatomical label of a direction: the LPS axis it mostly points along.
pub fn orientation_letter(direction: [f64; 3]) -> char {
    let (axis, value) = direction
        .iter()
        .enumerate()
        .fold((0, 0.0f64), |best, (a, &v)| {
            if v.abs() > best.1.abs() {
                (a, v)
            } else {
                best
            }
        });
    match (axis, value >= 0.0) {
        (0, true) => 'L',
        (0, false) => 'R',
        (1, true) => 'P',
        (1, false) => 'A',
        (_, true) => 'S',
        (_, false) => 'I',
    }
}

/// Why a store's bricks are larger than a fresh import's would be, if they are: format 1's lz4,
/// u8 bricks written before the prediction filters, dense u8 bricks written before the 3-D
/// predictor (kind 7, not kind 8), or fast u8 bricks of the x-delta filter (kind 6, not the
/// column delta of kind 9); the header's features tell which. With the rewrite's codec.
fn superseded_codec(
    h: &strata_storage::StoreHeader,
) -> Option<(&'static str, strata_storage::BrickCodec)> {
    use strata_storage::brick::{
        COLUMN_DELTA_U8_FEATURE, LINEAR3D_U8_FEATURE, PREDICTED_U8_FEATURE,
    };
    use strata_storage::BrickCodec;
    let narrow = h.stored == strata_storage::StoredScalar::U8;
    let has = |feature: &str| h.required_features.iter().any(|f| f == feature);
    if h.codec.is_format_1() {
        Some((
            "format 1: lz4 bricks, larger than today's codecs write",
            BrickCodec::Fast,
        ))
    } else if narrow && !has(PREDICTED_U8_FEATURE) {
        Some((
            "u8 bricks without the prediction filter, larger than today's codecs write",
            h.codec,
        ))
    } else if narrow && h.codec == BrickCodec::Dense && !has(LINEAR3D_U8_FEATURE) {
        Some((
            "dense u8 bricks of the older 2-D predictor (kind 7), about 4 % larger than \
             today's dense codec writes",
            BrickCodec::Dense,
        ))
    } else if narrow && h.codec == BrickCodec::Fast && !has(COLUMN_DELTA_U8_FEATURE) {
        Some((
            "fast u8 bricks of the x-delta filter (kind 6), slower to decode and about 3 % \
             larger than today's fast codec writes",
            BrickCodec::Fast,
        ))
    } else {
        None
    }
}

/// The command that rewrites the store at `path` in `codec`.
fn rewrite_command(
    path: &Path,
    h: &strata_storage::StoreHeader,
    codec: strata_storage::BrickCodec,
) -> String {
    let import = strata_storage::store::rebuild_command(path, h);
    if codec == strata_storage::BrickCodec::default() {
        import
    } else {
        format!("{import} --codec {}", codec.name())
    }
}

pub fn run(location: &str, token_file: Option<&Path>) -> Result<()> {
    let opened = open(
        location,
        token_file,
        strata_storage::store::DEFAULT_READ_CACHE_BYTES,
    )?;
    let withheld = matches!(&opened, Opened::Remote(r) if r.identifiers_withheld());
    let store = opened.source();
    let h = store.header();
    let g = &h.geometry;
    let code: String = g.direction.iter().map(|d| orientation_letter(*d)).collect();
    let m = &h.value_mapping;
    let (lo, hi) = (m.physical(h.stored_range[0]), m.physical(h.stored_range[1]));
    println!("store        {location}");
    if withheld {
        println!("description  (withheld by the server; it runs without --expose-identifiers)");
    } else {
        println!("description  {}", h.description);
    }
    println!(
        "modality     {}",
        if h.modality.is_empty() {
            "(unknown)"
        } else {
            &h.modality
        }
    );
    println!(
        "source       {} ({}), imported by strata {}",
        h.provenance.source_format,
        h.source_sample_type.name(),
        h.provenance.tool_version
    );
    println!(
        "format       store format {}, brick codec {}",
        h.format_version,
        h.codec.describe()
    );
    if let Opened::Local(local) = &opened {
        if let Some((why, codec)) = superseded_codec(h) {
            println!(
                "             {why}; rewrite it in the current {} codec with: {}",
                codec.name(),
                rewrite_command(local.path(), h, codec)
            );
        }
    }
    println!(
        "dimensions   {} x {} x {} voxels",
        g.dims[0], g.dims[1], g.dims[2]
    );
    println!(
        "spacing      {:.4} x {:.4} x {:.4} mm",
        g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2]
    );
    println!(
        "origin       ({:.3}, {:.3}, {:.3}) mm LPS",
        g.origin_lps_mm[0], g.origin_lps_mm[1], g.origin_lps_mm[2]
    );
    println!("orientation  {code} (index axes i, j, k point towards these patient sides)");
    for (a, d) in g.direction.iter().enumerate() {
        println!(
            "  axis {}    ({:+.5}, {:+.5}, {:+.5})",
            ['i', 'j', 'k'][a],
            d[0],
            d[1],
            d[2]
        );
    }
    println!(
        "stored       {:?}, physical = {} * stored + {} {}",
        h.stored, m.mapping.slope, m.mapping.intercept, m.unit
    );
    println!("value range  {lo} .. {hi} {}", m.unit);
    if h.quantization_error > 0.0 {
        println!("quantised    worst-case error {:.6}", h.quantization_error);
    }
    if h.non_finite_samples > 0 {
        println!(
            "non-finite   {} NaN/Inf samples clamped to the range ends",
            h.non_finite_samples
        );
    }
    for w in &h.windows {
        println!(
            "window       {}: centre {} width {}",
            w.name, w.center, w.width
        );
    }
    let s = store.stats();
    println!("levels       {}", h.layout.level_count());
    for (level, ((count, constant), dims)) in s
        .bricks_per_level
        .iter()
        .zip(&h.layout.level_dims)
        .enumerate()
    {
        let nb = h.layout.bricks_in_level(level);
        println!(
            "  level {level}    {}x{}x{} voxels, {}x{}x{} bricks: {count} ({constant} constant, {} stored)",
            dims[0], dims[1], dims[2], nb[0], nb[1], nb[2], count - constant
        );
    }
    let skeleton = store.skeleton();
    println!(
        "skeleton     {} of {} nodes kept ({:.2} MiB in memory; constant subtrees collapsed)",
        skeleton.stored_nodes(),
        h.layout.total_bricks(),
        skeleton.memory_bytes() as f64 / (1u64 << 20) as f64
    );
    println!(
        "size         {:.2} MB compressed, {:.2} MB uncompressed bricks (ratio {:.2}), source {:.2} MB",
        s.compressed_bytes as f64 / 1e6,
        s.uncompressed_bytes as f64 / 1e6,
        s.uncompressed_bytes as f64 / s.compressed_bytes.max(1) as f64,
        s.source_bytes as f64 / 1e6
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_storage::brick::{
        COLUMN_DELTA_U8_FEATURE, LINEAR3D_U8_FEATURE, PREDICTED_U8_FEATURE,
    };
    use strata_storage::{BrickCodec, StoredScalar};

    /// A dense u8 store an earlier build wrote (kind-7 bricks: its header lists the predicted
    /// feature but not the 3-D one) is flagged with a dense rewrite, a fast one of kind 6 with a
    /// fast rewrite; today's are not.
    #[test]
    fn u8_stores_of_older_predictors_are_flagged_with_a_rewrite_in_their_codec() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t1.strata");
        strata_storage::phantom::Phantom::cube(16)
            .write_store(&path, &Default::default())
            .unwrap();
        let mut header = strata_storage::Store::open(&path).unwrap().header().clone();
        header.stored = StoredScalar::U8;
        header.codec = BrickCodec::Dense;
        header.required_features = vec![PREDICTED_U8_FEATURE.into()];
        let (why, codec) = superseded_codec(&header).expect("kind-7 dense store not flagged");
        assert!(why.contains("kind 7"), "{why}");
        assert_eq!(codec, BrickCodec::Dense);
        let command = rewrite_command(&path, &header, codec);
        assert!(command.ends_with("--codec dense"), "{command}");
        header.required_features.push(LINEAR3D_U8_FEATURE.into());
        assert_eq!(superseded_codec(&header), None);
        // A fast u8 store needs no 3-D predictor, but the column delta.
        header.codec = BrickCodec::Fast;
        header.required_features = vec![PREDICTED_U8_FEATURE.into()];
        let (why, codec) = superseded_codec(&header).expect("kind-6 fast store not flagged");
        assert!(why.contains("kind 6"), "{why}");
        assert_eq!(codec, BrickCodec::Fast);
        header
            .required_features
            .push(COLUMN_DELTA_U8_FEATURE.into());
        assert_eq!(superseded_codec(&header), None);
        header.required_features.clear();
        let (why, codec) = superseded_codec(&header).expect("unfiltered u8 store not flagged");
        assert!(why.contains("without the prediction filter"), "{why}");
        assert_eq!(
            rewrite_command(&path, &header, codec),
            strata_storage::store::rebuild_command(&path, &header)
        );
    }
}
