//! How an error reaches the terminal: the chain of contexts once, each path once.
//!
//! Storage errors name their file ("X: truncated data ..."), and the commands add what they were
//! doing ("import of X into Y failed"); printed naively the chain says the path twice
//! ("cannot read X: X: ...") and an OS error that a library both displays and chains appears
//! twice. This joins the chain, dropping a cause whose text is already shown and a leading
//! "PATH: " that an outer context already named.

/// The error chain as one line, without repetitions.
pub fn describe(error: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in error.chain() {
        let mut part = cause.to_string();
        if part.is_empty() || text.contains(&part) {
            continue;
        }
        if let Some((prefix, rest)) = part.split_once(": ") {
            let names_a_path =
                prefix.contains('/') || prefix.contains('\\') || prefix.contains('.');
            if names_a_path && text.contains(prefix) && !rest.is_empty() {
                part = rest.to_string();
            }
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    #[test]
    fn a_path_named_by_the_context_is_not_repeated() {
        let inner: anyhow::Result<()> = Err(anyhow::anyhow!("/data/a.nii: truncated data"));
        let e = inner.context("cannot read /data/a.nii").unwrap_err();
        assert_eq!(describe(&e), "cannot read /data/a.nii: truncated data");
    }

    #[test]
    fn a_cause_already_shown_is_dropped() {
        let io = std::io::Error::other("No space left on device (os error 28)");
        /// Displays its cause and also chains it, as sled's and many libraries' errors do.
        #[derive(Debug)]
        struct Shown(std::io::Error);
        impl std::fmt::Display for Shown {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "store.strata: database error: {}", self.0)
            }
        }
        impl std::error::Error for Shown {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let e = anyhow::Error::new(Shown(io)).context("import failed");
        assert_eq!(
            describe(&e),
            "import failed: store.strata: database error: No space left on device (os error 28)"
        );
    }

    #[test]
    fn distinct_causes_are_all_kept() {
        let inner: anyhow::Result<()> = Err(anyhow::anyhow!("permission denied"));
        let e = inner.context("opening the GPU").unwrap_err();
        assert_eq!(describe(&e), "opening the GPU: permission denied");
    }
}
