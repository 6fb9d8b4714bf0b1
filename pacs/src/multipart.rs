//! A streaming `multipart/related` parser (RFC 2046 §5.1) for WADO-RS bodies.
//!
//! The body is fed chunk by chunk as it arrives; part data is handed on as it is found, so an
//! instance is never held whole in memory. Everything the parser keeps is bounded: the preamble,
//! a part's headers and the carried-over tail (shorter than the delimiter) are capped, and a
//! part's body is counted against `max_part_bytes`. A body that ends before the closing
//! delimiter is an error ([`MultipartParser::finish`]), so a truncated transfer never reads as
//! a complete one.

use memchr::memmem;

/// What a hostile or broken body can do wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MultipartError {
    #[error("no multipart boundary in the content type '{0}'")]
    NoBoundary(String),
    #[error("the boundary is not valid (1 to 70 printable characters)")]
    BadBoundary,
    #[error("no boundary delimiter within the first {0} bytes")]
    PreambleTooLong(usize),
    #[error("a boundary delimiter is followed by neither CRLF nor '--' (broken boundary)")]
    BrokenDelimiter,
    #[error("part headers longer than {0} bytes")]
    HeadersTooLong(usize),
    #[error("part headers are not text")]
    HeadersNotText,
    #[error("a part's content type is '{0}', not application/dicom")]
    WrongPartType(String),
    #[error("a part is larger than the limit of {limit} bytes")]
    PartTooLarge { limit: u64 },
    #[error("the body ended before the closing boundary (a part without end or a cut transfer)")]
    Truncated,
}

/// What the parser found, in body order.
#[derive(Debug, PartialEq, Eq)]
pub enum Event<'a> {
    /// A part begins; its content type, if it had one.
    PartStart { content_type: Option<String> },
    /// Some of the current part's bytes.
    Data(&'a [u8]),
    /// The current part is complete.
    PartEnd,
}

const MAX_PREAMBLE: usize = 64 << 10;
const MAX_HEADERS: usize = 16 << 10;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Preamble,
    AfterDelimiter,
    Headers,
    Body,
    Closed,
}

/// The `boundary` parameter of a `multipart/...` content type.
pub fn boundary_of(content_type: &str) -> Result<String, MultipartError> {
    let lower = content_type.to_ascii_lowercase();
    if !lower.trim_start().starts_with("multipart/") {
        return Err(MultipartError::NoBoundary(content_type.to_string()));
    }
    for param in content_type.split(';').skip(1) {
        let Some((name, value)) = param.split_once('=') else {
            continue;
        };
        if name.trim().eq_ignore_ascii_case("boundary") {
            let value = value.trim();
            let value = value
                .strip_prefix('"')
                .and_then(|v| v.strip_suffix('"'))
                .unwrap_or(value);
            // RFC 2046: 1..70 characters; printable ASCII keeps the delimiter search exact.
            if value.is_empty()
                || value.len() > 70
                || !value.bytes().all(|b| (0x20..0x7f).contains(&b))
            {
                return Err(MultipartError::BadBoundary);
            }
            return Ok(value.to_string());
        }
    }
    Err(MultipartError::NoBoundary(content_type.to_string()))
}

/// The parser; feed it chunks, then call [`finish`](Self::finish).
pub struct MultipartParser {
    /// `\r\n--boundary`: the delimiter as it appears before every part after the first.
    delimiter: Vec<u8>,
    /// Bytes not yet consumed; at most one chunk plus less than a delimiter.
    pending: Vec<u8>,
    state: State,
    preamble_seen: usize,
    part_bytes: u64,
    max_part_bytes: u64,
    require_dicom: bool,
}

impl MultipartParser {
    /// A parser for `boundary`; parts over `max_part_bytes` are an error. With `require_dicom`,
    /// a part that names a content type other than application/dicom is an error.
    pub fn new(boundary: &str, max_part_bytes: u64, require_dicom: bool) -> Self {
        let mut delimiter = b"\r\n--".to_vec();
        delimiter.extend_from_slice(boundary.as_bytes());
        MultipartParser {
            delimiter,
            // The body's first delimiter may come without the CRLF before it: start as if one
            // had been there, so one search finds every delimiter.
            pending: b"\r\n".to_vec(),
            state: State::Preamble,
            preamble_seen: 0,
            part_bytes: 0,
            max_part_bytes,
            require_dicom,
        }
    }

    /// Whether the closing delimiter was seen (what follows it is ignored).
    pub fn is_closed(&self) -> bool {
        self.state == State::Closed
    }

    /// Feeds one chunk; `on` sees the events it completes.
    pub fn feed<E>(
        &mut self,
        chunk: &[u8],
        on: &mut impl FnMut(Event<'_>) -> Result<(), E>,
    ) -> Result<(), E>
    where
        E: From<MultipartError>,
    {
        if self.state == State::Closed {
            return Ok(());
        }
        self.pending.extend_from_slice(chunk);
        let mut at = 0;
        loop {
            let rest = &self.pending[at..];
            match self.state {
                State::Closed => break,
                State::Preamble => match memmem::find(rest, &self.delimiter) {
                    Some(i) => {
                        at += i + self.delimiter.len();
                        self.state = State::AfterDelimiter;
                    }
                    None => {
                        let keep = self.delimiter.len() - 1;
                        let drop = rest.len().saturating_sub(keep);
                        self.preamble_seen += drop;
                        at += drop;
                        if self.preamble_seen > MAX_PREAMBLE {
                            return Err(MultipartError::PreambleTooLong(MAX_PREAMBLE).into());
                        }
                        break;
                    }
                },
                State::AfterDelimiter => {
                    // Transport padding (spaces, tabs) may follow a delimiter; bounded by the
                    // header limit so a stream of blanks cannot grow `pending`.
                    let padding = rest
                        .iter()
                        .take_while(|&&b| b == b' ' || b == b'\t')
                        .count();
                    if padding > MAX_HEADERS {
                        return Err(MultipartError::BrokenDelimiter.into());
                    }
                    let after = &rest[padding..];
                    if after.len() < 2 {
                        break;
                    }
                    if after.starts_with(b"--") {
                        self.state = State::Closed;
                        break;
                    }
                    if !after.starts_with(b"\r\n") {
                        return Err(MultipartError::BrokenDelimiter.into());
                    }
                    at += padding + 2;
                    self.state = State::Headers;
                }
                State::Headers => {
                    let (headers_len, skip) = if rest.starts_with(b"\r\n") {
                        (0, 2)
                    } else {
                        match memmem::find(rest, b"\r\n\r\n") {
                            Some(i) => (i, i + 4),
                            None => {
                                if rest.len() > MAX_HEADERS {
                                    return Err(MultipartError::HeadersTooLong(MAX_HEADERS).into());
                                }
                                break;
                            }
                        }
                    };
                    if headers_len > MAX_HEADERS {
                        return Err(MultipartError::HeadersTooLong(MAX_HEADERS).into());
                    }
                    let text = std::str::from_utf8(&rest[..headers_len])
                        .map_err(|_| MultipartError::HeadersNotText)?;
                    let content_type = text.split("\r\n").find_map(|line| {
                        let (name, value) = line.split_once(':')?;
                        name.trim()
                            .eq_ignore_ascii_case("content-type")
                            .then(|| value.trim().to_string())
                    });
                    if self.require_dicom {
                        if let Some(ct) = &content_type {
                            let essence = ct.split(';').next().unwrap_or("").trim();
                            if !essence.eq_ignore_ascii_case("application/dicom") {
                                return Err(MultipartError::WrongPartType(ct.clone()).into());
                            }
                        }
                    }
                    at += skip;
                    self.part_bytes = 0;
                    self.state = State::Body;
                    on(Event::PartStart { content_type })?;
                }
                State::Body => {
                    let (data_len, found) = match memmem::find(rest, &self.delimiter) {
                        Some(i) => (i, true),
                        // Keep what could be the start of a delimiter split across chunks.
                        None => (rest.len().saturating_sub(self.delimiter.len() - 1), false),
                    };
                    self.part_bytes += data_len as u64;
                    if self.part_bytes > self.max_part_bytes {
                        return Err(MultipartError::PartTooLarge {
                            limit: self.max_part_bytes,
                        }
                        .into());
                    }
                    if data_len > 0 {
                        on(Event::Data(&rest[..data_len]))?;
                    }
                    if !found {
                        at += data_len;
                        break;
                    }
                    at += data_len + self.delimiter.len();
                    self.state = State::AfterDelimiter;
                    on(Event::PartEnd)?;
                }
            }
        }
        self.pending.drain(..at);
        Ok(())
    }

    /// The body has ended: an error unless the closing delimiter was seen.
    pub fn finish(&self) -> Result<(), MultipartError> {
        if self.state == State::Closed {
            Ok(())
        } else {
            Err(MultipartError::Truncated)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parts of `body` fed in chunks of `chunk` bytes.
    fn parse(body: &[u8], chunk: usize, cap: u64) -> Result<Vec<Vec<u8>>, MultipartError> {
        let mut parser = MultipartParser::new("XyZ", cap, true);
        let mut parts: Vec<Vec<u8>> = Vec::new();
        let mut open = false;
        for piece in body.chunks(chunk.max(1)) {
            parser.feed(piece, &mut |e: Event<'_>| {
                match e {
                    Event::PartStart { .. } => {
                        assert!(!open);
                        open = true;
                        parts.push(Vec::new());
                    }
                    Event::Data(d) => parts.last_mut().expect("open part").extend_from_slice(d),
                    Event::PartEnd => open = false,
                }
                Ok::<(), MultipartError>(())
            })?;
        }
        parser.finish()?;
        Ok(parts)
    }

    fn body(parts: &[&[u8]]) -> Vec<u8> {
        let mut b = b"preamble\r\n".to_vec();
        for p in parts {
            b.extend_from_slice(b"--XyZ\r\nContent-Type: application/dicom\r\n\r\n");
            b.extend_from_slice(p);
            b.extend_from_slice(b"\r\n");
        }
        b.extend_from_slice(b"--XyZ--\r\nepilogue");
        b
    }

    #[test]
    fn parts_come_out_whole_at_every_chunk_size() {
        // Data that holds CRLFs, dashes and a near-boundary, so split delimiters are exercised.
        let a: &[u8] = b"DICM\r\n--XyY\r\n\r\n--Xy";
        let b: Vec<u8> = (0..5000u32).map(|i| (i % 251) as u8).collect();
        let whole = body(&[a, &b, b""]);
        for chunk in [1, 2, 3, 7, 64, 4096, whole.len()] {
            let parts = parse(&whole, chunk, 1 << 20).unwrap();
            assert_eq!(
                parts,
                vec![a.to_vec(), b.clone(), Vec::new()],
                "chunk {chunk}"
            );
        }
    }

    #[test]
    fn a_body_starting_with_the_delimiter_and_quoted_boundaries_parse() {
        let b = b"--XyZ\r\n\r\nabc\r\n--XyZ--".to_vec();
        assert_eq!(parse(&b, 5, 100).unwrap(), vec![b"abc".to_vec()]);
        assert_eq!(
            boundary_of("multipart/related; type=\"application/dicom\"; boundary=\"a b\"").unwrap(),
            "a b"
        );
        assert_eq!(
            boundary_of("multipart/related;boundary=XyZ").unwrap(),
            "XyZ"
        );
    }

    #[test]
    fn hostile_bodies_are_clear_errors() {
        // A part without end: the body stops inside it.
        let cut = b"--XyZ\r\n\r\nsome data that never ends".to_vec();
        for chunk in [1, 4, 100] {
            assert_eq!(parse(&cut, chunk, 100), Err(MultipartError::Truncated));
        }
        // The last part ends but the closing delimiter never comes.
        let unclosed = b"--XyZ\r\n\r\nabc\r\n--XyZ\r\n".to_vec();
        assert_eq!(parse(&unclosed, 3, 100), Err(MultipartError::Truncated));
        // A broken boundary: the delimiter is followed by garbage.
        let broken = b"--XyZ\r\n\r\nabc\r\n--XyZgarbage".to_vec();
        assert_eq!(parse(&broken, 3, 100), Err(MultipartError::BrokenDelimiter));
        // A boundary that never appears: the preamble is bounded.
        let none = vec![b'x'; MAX_PREAMBLE + 10];
        assert_eq!(
            parse(&none, 1000, 100),
            Err(MultipartError::PreambleTooLong(MAX_PREAMBLE))
        );
        // Endless headers are bounded.
        let mut headers = b"--XyZ\r\n".to_vec();
        headers.extend(std::iter::repeat_n(b'h', MAX_HEADERS + 10));
        assert_eq!(
            parse(&headers, 1000, 100),
            Err(MultipartError::HeadersTooLong(MAX_HEADERS))
        );
        // A part of another type.
        let html = b"--XyZ\r\nContent-Type: text/html\r\n\r\n<html>\r\n--XyZ--".to_vec();
        assert_eq!(
            parse(&html, 7, 100),
            Err(MultipartError::WrongPartType("text/html".into()))
        );
        // Boundaries that are not boundaries.
        assert!(boundary_of("application/dicom").is_err());
        assert!(boundary_of("multipart/related; type=x").is_err());
        assert!(boundary_of("multipart/related; boundary=\"\"").is_err());
        assert!(boundary_of(&format!("multipart/related; boundary={}", "a".repeat(71))).is_err());
    }

    #[test]
    fn an_oversize_part_is_cut_at_the_limit_without_buffering_it() {
        let mut parser = MultipartParser::new("XyZ", 1000, true);
        parser
            .feed(b"--XyZ\r\n\r\n", &mut |_| Ok::<(), MultipartError>(()))
            .unwrap();
        let chunk = vec![0u8; 300];
        let mut seen = 0usize;
        let mut result = Ok(());
        // An endless part: the error comes after about the limit, and `pending` never grows
        // beyond a chunk plus a delimiter.
        for _ in 0..100 {
            result = parser.feed(&chunk, &mut |e| {
                if let Event::Data(d) = e {
                    seen += d.len();
                }
                Ok::<(), MultipartError>(())
            });
            assert!(parser.pending.len() <= chunk.len() + parser.delimiter.len());
            if result.is_err() {
                break;
            }
        }
        assert_eq!(result, Err(MultipartError::PartTooLarge { limit: 1000 }));
        assert!(seen <= 1000, "{seen}");
    }
}
