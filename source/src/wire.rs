//! What travels between `strata serve` and its client: the URL scheme and the one-response
//! "open" document (header, histogram, stats and the octree skeleton).
//!
//! Paths, all under `/v1`:
//! - `GET /v1/stores`: JSON list of the served stores (name, generation, dimensions).
//! - `GET /v1/stores/{name}`: the open document ([`encode_open_document`]).
//! - `GET /v1/stores/{name}/g/{generation}/bricks/{level}/{z}/{y}/{x}`: one brick record as
//!   stored (kind, xxh3 checksum over key and body, compressed body), never decoded on the server.
//!   The generation makes the URL immutable: a re-import gets new URLs.
//! - `GET /v1/stores/{name}/g/{generation}/f/{frame}`: frame `frame` of a 4-D store as an open
//!   document ([`frame_document_path`]): the same JSON (its header's `frames` is the count),
//!   that frame's skeleton.
//! - `GET /v1/stores/{name}/g/{generation}/f/{frame}/bricks/{level}/{z}/{y}/{x}`: one brick of
//!   frame `frame` ([`frame_brick_path`]); frame 0's bricks keep the path above, so clients
//!   that know no frames still work.
//!
//! A later OME-Zarr view of the same stores sits beside these, under
//! `/v1/stores/{name}/zarr/...`.

use serde::{Deserialize, Serialize};
use strata_storage::histogram::Histogram;
use strata_storage::store::{Skeleton, StoreStats};
use strata_storage::StoreHeader;
use strata_types::BrickId;

pub const API_PREFIX: &str = "/v1";
pub const OPEN_DOCUMENT_MAGIC: &[u8; 8] = b"STRATA\x01\n";
pub const OPEN_DOCUMENT_TYPE: &str = "application/vnd.strata.store-open.v1";
/// The open document's JSON part is bounded (a header, a 1024-bin histogram, stats).
pub const MAX_OPEN_JSON_BYTES: u64 = 16 << 20;

/// The JSON part of the open document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OpenDocument {
    pub name: String,
    pub generation: String,
    /// Description and provenance are emptied unless the server runs with
    /// `--expose-identifiers` (source paths often carry patient names).
    pub identifiers_withheld: bool,
    pub header: StoreHeader,
    pub histogram: Histogram,
    pub stats: StoreStats,
}

/// One entry of `GET /v1/stores`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreListing {
    pub name: String,
    pub generation: String,
    pub dims: [u32; 3],
    pub levels: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreList {
    pub stores: Vec<StoreListing>,
}

/// `magic | json length u64 LE | json | skeleton (Skeleton::encode, checksummed)`.
pub fn encode_open_document(
    doc: &OpenDocument,
    skeleton: &Skeleton,
) -> serde_json::Result<Vec<u8>> {
    let json = serde_json::to_vec(doc)?;
    let skeleton = skeleton.encode();
    let mut out = Vec::with_capacity(16 + json.len() + skeleton.len());
    out.extend_from_slice(OPEN_DOCUMENT_MAGIC);
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(&skeleton);
    Ok(out)
}

/// Why an open document was not read; the wording names the part that failed.
#[derive(Debug, thiserror::Error)]
pub enum OpenDocumentError {
    #[error("not a Strata open document (wrong magic)")]
    WrongMagic,
    #[error("open document truncated")]
    Truncated,
    #[error("open document's JSON part claims {0} bytes")]
    JsonLength(u64),
    #[error("open document: {0}")]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Format(#[from] StoreFormatError),
    #[error("octree skeleton {0}")]
    Skeleton(#[from] strata_storage::skeleton::SkeletonDecodeError),
}

/// A served store this build cannot read as a whole (see [`check_store_format`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StoreFormatError {
    #[error(
        "the server's store has format version {version}, and this client reads versions \
         {oldest} to {newest}: update this client"
    )]
    Version {
        version: u32,
        oldest: u32,
        newest: u32,
    },
    #[error("the store needs '{0}', a store feature of a newer Strata: update this client")]
    Feature(String),
}

/// Decodes [`encode_open_document`]'s bytes, refusing a store this build cannot read
/// ([`check_store_format`] with `known_features`) before it decodes the skeleton.
pub fn decode_open_document(
    bytes: &[u8],
    known_features: &[&str],
) -> Result<(OpenDocument, Skeleton), OpenDocumentError> {
    let rest = bytes
        .strip_prefix(OPEN_DOCUMENT_MAGIC.as_slice())
        .ok_or(OpenDocumentError::WrongMagic)?;
    let (len, rest) = rest
        .split_at_checked(8)
        .ok_or(OpenDocumentError::Truncated)?;
    let len = u64::from_le_bytes(len.try_into().map_err(|_| OpenDocumentError::Truncated)?);
    if len > MAX_OPEN_JSON_BYTES || len > rest.len() as u64 {
        return Err(OpenDocumentError::JsonLength(len));
    }
    let (json, skeleton) = rest.split_at(len as usize);
    let doc: OpenDocument = serde_json::from_slice(json)?;
    // Before the skeleton: a newer store's skeleton may be one this build cannot decode, and
    // the feature or version names the reason where the decode error would not.
    check_store_format(&doc.header, known_features)?;
    let skeleton = Skeleton::decode(skeleton, &doc.header.layout)?;
    Ok((doc, skeleton))
}

/// Refuses a served store this client cannot read as a whole, by name, before any brick is
/// fetched: a newer format version, or a store feature (a brick kind, 4-D frames) of a newer
/// Strata. Without it an older client would fail brick by brick, or misread a header field it
/// does not know.
pub fn check_store_format(
    header: &StoreHeader,
    known_features: &[&str],
) -> Result<(), StoreFormatError> {
    use strata_storage::store::{OLDEST_READABLE_FORMAT_VERSION, STORE_FORMAT_VERSION};
    let version = header.format_version;
    if !(OLDEST_READABLE_FORMAT_VERSION..=STORE_FORMAT_VERSION).contains(&version) {
        return Err(StoreFormatError::Version {
            version,
            oldest: OLDEST_READABLE_FORMAT_VERSION,
            newest: STORE_FORMAT_VERSION,
        });
    }
    match header
        .required_features
        .iter()
        .find(|feature| !known_features.contains(&feature.as_str()))
    {
        Some(feature) => Err(StoreFormatError::Feature(feature.clone())),
        None => Ok(()),
    }
}

/// Path of one brick (relative to the server's root).
pub fn brick_path(name: &str, generation: &str, id: BrickId) -> String {
    format!(
        "{API_PREFIX}/stores/{name}/g/{generation}/bricks/{}/{}/{}/{}",
        id.level, id.coords[2], id.coords[1], id.coords[0]
    )
}

/// Path of frame `frame`'s open document: the store's document with that frame's skeleton.
pub fn frame_document_path(name: &str, generation: &str, frame: u32) -> String {
    format!("{API_PREFIX}/stores/{name}/g/{generation}/f/{frame}")
}

/// Path of one brick of frame `frame`; frame 0's is [`brick_path`] (the route older servers
/// and clients know).
pub fn frame_brick_path(name: &str, generation: &str, frame: u32, id: BrickId) -> String {
    if frame == 0 {
        return brick_path(name, generation, id);
    }
    format!(
        "{}/bricks/{}/{}/{}/{}",
        frame_document_path(name, generation, frame),
        id.level,
        id.coords[2],
        id.coords[1],
        id.coords[0]
    )
}

/// Strong ETag of a brick: generation and record checksum.
pub fn brick_etag(generation: &str, checksum: u64) -> String {
    format!("\"{generation}-{checksum:016x}\"")
}

/// The longest `Retry-After` a client honours as given; a longer one waits this long (a
/// misconfigured proxy must not park a viewer for an hour).
pub const MAX_RETRY_AFTER: std::time::Duration = std::time::Duration::from_secs(30);

/// A `Retry-After` header's value as a wait, capped at [`MAX_RETRY_AFTER`]. Only the
/// delta-seconds form: `strata serve` sends it and proxies pass it on; the HTTP-date form
/// (and anything unreadable) gives `None`, so the caller's own backoff applies.
pub fn retry_after(value: &str) -> Option<std::time::Duration> {
    let seconds: u64 = value.trim().parse().ok()?;
    Some(std::time::Duration::from_secs(seconds).min(MAX_RETRY_AFTER))
}

/// Store names that may appear in a URL: what `strata serve` accepts for a store's name.
pub fn is_valid_store_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 128
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.')
        && !name.starts_with('.')
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What an older client meets when a newer server sends a store with a skeleton encoding
    /// it lacks: the feature by name, not the skeleton's decode error.
    #[test]
    fn an_unknown_feature_is_named_before_the_skeleton_is_decoded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("phantom.strata");
        strata_storage::phantom::Phantom::cube(16)
            .write_store(&path, &strata_storage::import::ImportOptions::default())
            .unwrap();
        let store = strata_storage::Store::open(&path).unwrap();
        let mut doc = OpenDocument {
            name: "phantom".into(),
            generation: "g1".into(),
            identifiers_withheld: true,
            header: store.header().clone(),
            histogram: store.histogram().clone(),
            stats: store.stats().clone(),
        };
        let known = strata_storage::store::KNOWN_STORE_FEATURES;
        let bytes = encode_open_document(&doc, store.skeleton()).unwrap();
        let (decoded, skeleton) = decode_open_document(&bytes, known).unwrap();
        assert_eq!(decoded, doc);
        assert_eq!(skeleton.encode(), store.skeleton().encode());

        // The document with skeleton bytes no build can decode.
        let with_unreadable_skeleton = |doc: &OpenDocument| {
            let mut bytes = encode_open_document(doc, store.skeleton()).unwrap();
            bytes.truncate(bytes.len() - store.skeleton().encode().len());
            bytes.extend_from_slice(b"an encoding from the future");
            bytes
        };
        // A newer encoding behind a feature this build does not know: the feature is named.
        doc.header.required_features.push("skeleton-v9".into());
        let refusal = decode_open_document(&with_unreadable_skeleton(&doc), known)
            .unwrap_err()
            .to_string();
        assert!(refusal.contains("'skeleton-v9'"), "{refusal}");
        assert!(refusal.contains("update this client"), "{refusal}");
        // Known features: the same bytes are then reported as the skeleton's.
        doc.header.required_features.pop();
        let error = decode_open_document(&with_unreadable_skeleton(&doc), known)
            .unwrap_err()
            .to_string();
        assert!(error.contains("skeleton"), "{error}");
    }

    #[test]
    fn store_names_exclude_paths() {
        assert!(is_valid_store_name("chest-ct.strata"));
        for bad in ["", "..", "../x", "a/b", ".hidden", "a b", "a%2Fb"] {
            assert!(!is_valid_store_name(bad), "{bad}");
        }
    }

    #[test]
    fn retry_after_reads_seconds_caps_them_and_ignores_dates_and_junk() {
        use std::time::Duration;
        assert_eq!(retry_after("2"), Some(Duration::from_secs(2)));
        assert_eq!(retry_after(" 0 "), Some(Duration::ZERO));
        assert_eq!(retry_after("3600"), Some(MAX_RETRY_AFTER));
        assert_eq!(retry_after("Wed, 21 Oct 2015 07:28:00 GMT"), None);
        assert_eq!(retry_after("-1"), None);
        assert_eq!(retry_after(""), None);
    }
}
