//! Errors of the store: each names the file and what was wrong with it.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// An I/O error on a named path. The cause is part of the message and
    /// not a separate source, so that a chain of errors says it once.
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The content of a file is invalid: `field` is the offending field
    /// (header key, tag, JSON key ...), `msg` says what was expected.
    #[error("{}: {field}: {msg}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        msg: String,
    },
    /// The input is valid but uses something brickyard does not support.
    #[error("{}: unsupported {field}: {msg}", path.display())]
    Unsupported {
        path: PathBuf,
        field: String,
        msg: String,
    },
    /// What a read used of a file (a shard index kept from before) left
    /// data out that the file holds now: the reader forgot what it kept,
    /// and the same read done again gets the data (the loader does so).
    #[error("{}: {field}: {msg} {}", path.display(), crate::source::READ_AGAIN)]
    Changed {
        path: PathBuf,
        field: String,
        msg: String,
    },
    /// The output exists and `--overwrite` was not given, or similar.
    #[error("{}: {msg}", path.display())]
    Refused { path: PathBuf, msg: String },
    /// An error from the Zarr library.
    #[error("{}: zarr: {msg}", path.display())]
    Zarr { path: PathBuf, msg: String },
    /// Conversion was interrupted (Ctrl-C).
    #[error("interrupted")]
    Interrupted,
    /// Another process of a shared conversion failed (the message names
    /// its rank and cause).
    #[error("{0}")]
    Team(String),
}

pub type Result<T, E = StoreError> = std::result::Result<T, E>;

impl StoreError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        StoreError::Io {
            path: path.into(),
            error: source,
        }
    }
    /// `path` does not exist (an I/O error of kind `NotFound` that says so
    /// in words, not as the bare kind's "entity not found").
    pub fn not_found(path: impl Into<PathBuf>) -> Self {
        let path = path.into();
        let what = match foreign_scheme(&path) {
            Some(scheme) => format!(
                "no such file or directory; {scheme}:// is no scheme stores are read from: \
                 give a local path or an http://, https:// or s3:// URL"
            ),
            None => format!(
                "no such file or directory{}{}",
                unfinished_conversion(&path),
                unfinished_result(&path)
            ),
        };
        StoreError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, what),
        )
    }
    pub fn invalid(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        msg: impl Into<String>,
    ) -> Self {
        StoreError::Invalid {
            path: path.into(),
            field: field.into(),
            msg: msg.into(),
        }
    }
    pub fn unsupported(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        msg: impl Into<String>,
    ) -> Self {
        StoreError::Unsupported {
            path: path.into(),
            field: field.into(),
            msg: msg.into(),
        }
    }
    pub fn zarr(path: impl Into<PathBuf>, msg: impl std::fmt::Display) -> Self {
        StoreError::Zarr {
            path: path.into(),
            msg: msg.to_string(),
        }
    }
}

/// Extension to attach a path to `std::io::Result`.
pub trait IoContext<T> {
    fn at(self, path: impl Into<PathBuf>) -> Result<T>;
}

impl<T> IoContext<T> for std::io::Result<T> {
    fn at(self, path: impl Into<PathBuf>) -> Result<T> {
        self.map_err(|e| StoreError::io(path, e))
    }
}

/// The scheme of `p` where it reads as a URL (`scheme://…`) of a scheme
/// other than those read (`ftp`, `gs`, `file`, …).
fn foreign_scheme(p: &std::path::Path) -> Option<&str> {
    let s = p.to_str()?;
    let (scheme, _) = s.split_once("://")?;
    let ok = scheme.len() > 1
        && scheme.starts_with(|c: char| c.is_ascii_alphabetic())
        && scheme
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'));
    (ok && !["http", "https", "s3"]
        .iter()
        .any(|k| scheme.eq_ignore_ascii_case(k)))
    .then_some(scheme)
}

/// Where a missing local store `path` is being converted, or what a
/// conversion that stopped left of it: that, in words, to follow "no such
/// file".
fn unfinished_conversion(path: &std::path::Path) -> String {
    if crate::storage::is_remote(path) {
        return String::new();
    }
    let (partial, old) = (
        crate::builder::partial_path(path),
        crate::builder::old_path(path),
    );
    if old.is_dir() {
        format!(
            "; {} is the store a conversion was replacing when it stopped: rename it back",
            old.display()
        )
    } else if partial.is_dir() {
        match crate::lock::live_holder(&crate::builder::lock_path(path)) {
            // (Not interrupted: at work. Removing its folder would break
            // it.)
            Some(pid) => format!(
                "; a conversion into it is at work (process {pid}, writing {}): wait for it to end",
                partial.display()
            ),
            None => format!(
                "; {} is what an interrupted conversion of it wrote: run that convert again (it \
                 takes over), or remove the folder",
                partial.display()
            ),
        }
    } else {
        String::new()
    }
}

/// Where a missing `path` is a processing result still being written, or
/// one whose job was stopped (`brickyard process` stages its result as
/// `.NAME.new` beside it, under the lock `.NAME.lock`): that, in words,
/// to follow "no such file".
fn unfinished_result(path: &std::path::Path) -> String {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
        return String::new();
    };
    if crate::storage::is_remote(path) {
        return String::new();
    }
    let name = name.to_string_lossy();
    if let Some(pid) = crate::lock::live_holder(&dir.join(format!(".{name}.lock"))) {
        return format!("; a processing job is writing it now (process {pid}): wait for it to end");
    }
    let staged = dir.join(format!(".{name}.new"));
    match [staged.clone(), crate::builder::partial_path(&staged)]
        .into_iter()
        .find(|p| p.exists())
    {
        Some(left) => format!(
            "; the processing job that was writing it stopped before it ended (it left {}): \
             run the same `brickyard process` command again",
            left.display()
        ),
        None => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_of_other_url_schemes_are_named_as_such() {
        let e = StoreError::not_found("ftp://host/a.ome.zarr").to_string();
        assert!(e.contains("ftp:// is no scheme"), "{e}");
        let e = StoreError::not_found("data/a.ome.zarr").to_string();
        assert!(!e.contains("scheme"), "{e}");
        // (A drive letter or one-letter folder is no scheme.)
        assert!(foreign_scheme(std::path::Path::new("c://x")).is_none());
        assert!(foreign_scheme(std::path::Path::new("gs://b/x")).is_some());
    }
}
