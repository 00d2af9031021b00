//! brickyard-web: the web client's data path and viewer core. The store
//! is read over HTTP ([`source`]: OME-Zarr 0.4/0.5 metadata, shard
//! indexes and chunks by byte range, decoded in Rust: [`codec`]), bricks
//! are loaded asynchronously into the same virtual memory and drawn by the
//! same renderers as natively ([`session`]); the view lives in the page's
//! URL ([`view`]). In the browser ([`web`], `wasm32` only) the page drives
//! it through `wasm-bindgen`.
//!
//! Everything but [`web`] builds and is tested natively too.

pub mod codec;
pub mod session;
pub mod source;
pub mod view;
#[cfg(target_arch = "wasm32")]
pub mod web;
pub mod zarr;
