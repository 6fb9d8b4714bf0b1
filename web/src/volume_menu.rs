//! The page's Volume menu, its platform-independent part: the entries it offers (the sample
//! made in the page, then each of the server's stores from `GET /v1/stores`, by name with its
//! size) and what choosing one does to the view (`store=` in the address, which the next
//! frame opens). `browser.rs` draws the combo box from these; the native tests check them
//! against a real server's answer.

use strata_source::wire::StoreList;

use crate::view_state::ViewState;

/// The sample's entry (no `store=`).
pub const SAMPLE_ENTRY: &str = "sample (made in the page)";

/// One entry of the menu: the store it opens (None: the sample) and its label.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MenuEntry {
    pub store: Option<String>,
    pub label: String,
}

/// A `GET /v1/stores` answer that is not a store list.
#[derive(Debug, thiserror::Error)]
#[error("the server's store list: {0}")]
pub struct StoreListError(#[from] serde_json::Error);

/// The server's answer to `GET /v1/stores`, as the page reads it.
pub fn parse_store_list(body: &[u8]) -> Result<StoreList, StoreListError> {
    Ok(serde_json::from_slice(body)?)
}

/// The menu's entries: the sample first, then the server's stores in the server's order.
pub fn entries(list: &StoreList) -> Vec<MenuEntry> {
    std::iter::once(MenuEntry {
        store: None,
        label: SAMPLE_ENTRY.into(),
    })
    .chain(list.stores.iter().map(|store| {
        let [x, y, z] = store.dims;
        MenuEntry {
            store: Some(store.name.clone()),
            label: format!("{} ({x}×{y}×{z})", store.name),
        }
    }))
    .collect()
}

/// The closed menu's text for the volume shown.
pub fn shown_label(store: Option<&str>) -> String {
    store.map_or_else(|| SAMPLE_ENTRY.to_string(), str::to_string)
}

/// Applies a choice to the view; true when it switched volume (the page then drops the
/// store it streams and opens the chosen one, whose name the address now carries).
pub fn choose(view: &mut ViewState, chosen: Option<String>) -> bool {
    if chosen == view.store {
        return false;
    }
    view.store = chosen;
    true
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};

    use super::*;
    use crate::view_state::Fragment;
    use strata_service::server::{find_stores, start};
    use strata_service::ServeOptions;
    use strata_storage::phantom::Phantom;

    /// `GET /v1/stores` on the server, the body as the page's fetch() gets it.
    fn get_store_list(base_url: &str) -> Vec<u8> {
        let address = base_url.trim_start_matches("http://");
        let mut stream = std::net::TcpStream::connect(address).expect("connect");
        write!(
            stream,
            "GET /v1/stores HTTP/1.0\r\nHost: {address}\r\nConnection: close\r\n\r\n"
        )
        .expect("request");
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).expect("answer");
        let split = answer
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .expect("headers end");
        assert!(
            answer.starts_with(b"HTTP/1.1 200") || answer.starts_with(b"HTTP/1.0 200"),
            "{}",
            String::from_utf8_lossy(&answer[..split])
        );
        answer[split + 4..].to_vec()
    }

    #[test]
    fn the_menu_lists_the_sample_and_the_servers_stores_and_a_choice_names_the_store() {
        let scratch = tempfile::tempdir().expect("scratch folder");
        let mut paths = Vec::new();
        for (name, edge) in [("chest", 24), ("knee", 16)] {
            let path = scratch.path().join(format!("{name}.strata"));
            Phantom::cube(edge)
                .write_store(&path, &Default::default())
                .expect("store");
            paths.push(path);
        }
        let server = start(
            find_stores(&paths).expect("stores found"),
            ServeOptions::default(),
        )
        .expect("server starts");
        let list = parse_store_list(&get_store_list(&server.base_url())).expect("store list");
        let menu = entries(&list);
        let mut labels: Vec<&str> = menu.iter().map(|e| e.label.as_str()).collect();
        assert_eq!(labels.remove(0), SAMPLE_ENTRY, "the sample comes first");
        labels.sort_unstable();
        assert_eq!(labels, ["chest (24×24×24)", "knee (16×16×16)"]);
        assert_eq!(menu[0].store, None);

        // Choosing a store puts it in the address; choosing it again changes nothing; the
        // sample takes it out again.
        let mut view = Fragment::parse("mode=mip").expect("fragment").view;
        assert_eq!(shown_label(view.store.as_deref()), SAMPLE_ENTRY);
        let knee = menu
            .iter()
            .find(|e| e.store.as_deref() == Some("knee"))
            .expect("knee listed");
        assert!(choose(&mut view, knee.store.clone()));
        assert!(!choose(&mut view, knee.store.clone()));
        assert_eq!(shown_label(view.store.as_deref()), "knee");
        let address = view.to_fragment();
        assert!(address.contains("store=knee"), "{address}");
        let reopened = Fragment::parse(address.trim_start_matches('#')).expect("its own fragment");
        assert_eq!(reopened.view.store.as_deref(), Some("knee"));
        assert!(choose(&mut view, None));
        assert!(!view.to_fragment().contains("store="));
    }

    #[test]
    fn a_bad_store_list_is_an_error_not_a_panic() {
        assert!(parse_store_list(b"<html>").is_err());
        let empty = parse_store_list(br#"{"stores": []}"#).expect("empty list");
        assert_eq!(entries(&empty).len(), 1, "the sample alone");
    }
}
