//! A hostile DICOMweb server on loopback: each misbehaviour is a clear error naming the server,
//! within its bound (a stall after 1 s, a part cut at 4 MiB), with no panic and nothing
//! partial left in the folder.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::Duration;

use strata_pacs::{Auth, Client, ClientOptions, PacsError};

const BOUNDARY: &str = "B0uNdArY";

/// Answers one request on `stream` by the study UID in its path (each study one misbehaviour).
fn answer(mut stream: TcpStream, port: u16) {
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") && head.len() < 16 << 10 {
        if stream.read(&mut byte).unwrap_or(0) == 0 {
            return;
        }
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head).to_string();
    let path = head.split_whitespace().nth(1).unwrap_or("").to_string();
    let study = path
        .strip_prefix("/dicom-web/studies/")
        .and_then(|p| p.split('/').next())
        .unwrap_or("")
        .to_string();
    let reply = |stream: &mut TcpStream, status: &str, content_type: &str, body: &[u8]| {
        let _ = stream.write_all(
            format!(
                "HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            )
            .as_bytes(),
        );
        let _ = stream.write_all(body);
    };
    if path.contains("/instances?") || path.ends_with("/instances") {
        let list = br#"[{"00080018":{"vr":"UI","Value":["9.9"]}}]"#;
        return reply(&mut stream, "200 OK", "application/dicom+json", list);
    }
    if path.contains("/series?") {
        return reply(&mut stream, "200 OK", "application/dicom+json", b"[]");
    }
    let multipart = format!("multipart/related; type=\"application/dicom\"; boundary={BOUNDARY}");
    let mut dicom = vec![0u8; 128];
    dicom.extend_from_slice(b"DICM");
    let start = format!("--{BOUNDARY}\r\nContent-Type: application/dicom\r\n\r\n");
    match study.as_str() {
        // A broken boundary: the delimiter is followed by garbage.
        "1" => {
            let mut body = start.clone().into_bytes();
            body.extend_from_slice(&dicom);
            body.extend_from_slice(format!("\r\n--{BOUNDARY}garbage").as_bytes());
            reply(&mut stream, "200 OK", &multipart, &body);
        }
        // A part without end: the body stops inside it.
        "2" => {
            let mut body = start.clone().into_bytes();
            body.extend_from_slice(&dicom);
            reply(&mut stream, "200 OK", &multipart, &body);
        }
        // An endless part: streamed until the client hangs up (at most 64 MiB).
        "3" => {
            let _ = stream.write_all(
                format!(
                    "HTTP/1.1 200 OK\r\nContent-Type: {multipart}\r\nConnection: close\r\n\r\n"
                )
                .as_bytes(),
            );
            let _ = stream.write_all(start.as_bytes());
            let _ = stream.write_all(&dicom);
            let chunk = vec![7u8; 1 << 20];
            for _ in 0..64 {
                if stream.write_all(&chunk).is_err() {
                    break;
                }
            }
        }
        // A redirect to another host (127.0.0.2 is loopback too, but not the server's host).
        "4" => {
            let _ = stream.write_all(
                format!(
                    "HTTP/1.1 302 Found\r\nLocation: http://127.0.0.2:{port}{path}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                )
                .as_bytes(),
            );
        }
        "5" => reply(&mut stream, "401 Unauthorized", "text/plain", b"no"),
        // A stall: headers and the start of a part, then nothing for longer than the bound.
        "6" => {
            let _ = stream.write_all(
                format!(
                    "HTTP/1.1 200 OK\r\nContent-Type: {multipart}\r\nConnection: close\r\n\r\n"
                )
                .as_bytes(),
            );
            let _ = stream.write_all(start.as_bytes());
            let _ = stream.flush();
            std::thread::sleep(Duration::from_secs(4));
        }
        // Not multipart at all.
        "7" => reply(&mut stream, "200 OK", "text/html", b"<html>login</html>"),
        // A part of another type.
        "8" => {
            let body = format!(
                "--{BOUNDARY}\r\nContent-Type: text/html\r\n\r\n<html>\r\n--{BOUNDARY}--\r\n"
            );
            reply(&mut stream, "200 OK", &multipart, body.as_bytes());
        }
        // Always 503: retried, then reported.
        "9" => reply(
            &mut stream,
            "503 Service Unavailable",
            "text/plain",
            b"busy",
        ),
        // A DICOM file, but of another series ("10") or another instance ("11").
        "10" | "11" => {
            let (series, sop) = if study == "10" {
                ("7.7", "9.9")
            } else {
                ("2", "9.8")
            };
            let mut body = start.clone().into_bytes();
            body.extend_from_slice(&dicom_file(series, sop));
            body.extend_from_slice(format!("\r\n--{BOUNDARY}--\r\n").as_bytes());
            reply(&mut stream, "200 OK", &multipart, &body);
        }
        _ => reply(&mut stream, "404 Not Found", "text/plain", b""),
    }
}

/// A small but whole DICOM file (explicit VR little endian) of instance `sop` of `series`.
fn dicom_file(series: &str, sop: &str) -> Vec<u8> {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
    const CT_IMAGE: &str = "1.2.840.10008.5.1.4.1.1.2";
    let object = InMemDicomObject::from_element_iter([
        DataElement::new(tags::SOP_CLASS_UID, VR::UI, PrimitiveValue::from(CT_IMAGE)),
        DataElement::new(tags::SOP_INSTANCE_UID, VR::UI, PrimitiveValue::from(sop)),
        DataElement::new(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            PrimitiveValue::from(series),
        ),
    ]);
    let file = object
        .with_meta(
            FileMetaTableBuilder::new()
                .transfer_syntax("1.2.840.10008.1.2.1")
                .media_storage_sop_class_uid(CT_IMAGE)
                .media_storage_sop_instance_uid(sop),
        )
        .unwrap();
    let mut bytes = Vec::new();
    file.write_all(&mut bytes).unwrap();
    bytes
}

fn stub() -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::Builder::new()
        .name("strata-pacs-stub".into())
        .spawn(move || {
            for stream in listener.incoming().flatten() {
                let _ = std::thread::Builder::new()
                    .name("strata-pacs-stub-conn".into())
                    .spawn(move || answer(stream, port));
            }
        })
        .unwrap();
    port
}

#[test]
fn a_hostile_server_gives_clear_bounded_errors() {
    let port = stub();
    let url = format!("http://127.0.0.1:{port}/dicom-web");
    let options = ClientOptions {
        stall_timeout: Duration::from_secs(1),
        max_part_bytes: 4 << 20,
        attempts: 2,
        backoff: Duration::from_millis(10),
        ..ClientOptions::default()
    };
    let client = Client::new(&url, Auth::None, None, options).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cases: [(&str, &str); 11] = [
        ("1", "broken boundary"),
        ("2", "before the closing boundary"),
        ("3", "larger than the limit of 4194304 bytes"),
        ("4", "refused a redirect to another host"),
        ("5", "HTTP 401"),
        ("6", "stalled"),
        ("7", "no multipart boundary"),
        ("8", "not application/dicom"),
        ("9", "HTTP 503"),
        ("10", "belongs to series 7.7, not the one asked for"),
        ("11", "answered instance 9.8 instead"),
    ];
    for (study, expected) in cases {
        let e: PacsError = client
            .retrieve_series(study, "2", dir.path(), None, None)
            .unwrap_err();
        let text = e.to_string();
        assert!(
            text.contains(expected) && text.contains(&url),
            "study {study}: {text}"
        );
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "study {study} left files"
        );
    }
    // Two searches, the whole series once (no retry: what it does not bring is fetched per
    // instance), then the instance's 503 tried twice (attempts = 2) before being reported.
    let before = client.requests();
    let _ = client.retrieve_series("9", "2", dir.path(), None, None);
    assert_eq!(client.requests() - before, 2 + 1 + 2);
}
