//! The Zarr library's view of a store location: its storage traits over
//! [`super::read_spans`] and [`super::size`].

use super::Span;
use std::path::{Path, PathBuf};
use zarrs::storage::byte_range::{ByteRange, ByteRangeIterator};
use zarrs::storage::{Bytes, MaybeBytesIterator, ReadableStorageTraits, StorageError, StoreKey};

/// A readable Zarr store rooted at a location (a directory or a URL).
#[derive(Clone, Debug)]
pub struct StoreAt {
    root: PathBuf,
}

impl StoreAt {
    pub fn new(root: &Path) -> Self {
        StoreAt {
            root: root.to_path_buf(),
        }
    }

    fn at(&self, key: &StoreKey) -> PathBuf {
        self.root.join(key.as_str())
    }
}

fn span(r: ByteRange) -> Span {
    match r {
        ByteRange::FromStart(0, None) => Span::All,
        ByteRange::FromStart(o, None) => Span::From(o),
        ByteRange::FromStart(o, Some(n)) => Span::Range(o..o.saturating_add(n)),
        ByteRange::Suffix(n) => Span::Suffix(n),
    }
}

impl ReadableStorageTraits for StoreAt {
    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        let spans: Vec<Span> = byte_ranges.map(span).collect();
        match super::read_spans(&self.at(key), &spans) {
            Ok(None) => Ok(None),
            Ok(Some(parts)) => Ok(Some(Box::new(
                parts.into_iter().map(|b| Ok(Bytes::from(b))),
            ))),
            Err(e) => Err(StorageError::Other(e.to_string())),
        }
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        super::size(&self.at(key)).map_err(|e| StorageError::Other(e.to_string()))
    }

    fn supports_get_partial(&self) -> bool {
        true
    }
}
