//! brickyard-cache: the part of the data path between the store and the
//! consumers.
//!
//! ```text
//! store ──loader──▶ host cache ──upload──▶ device pool + page tables
//!        (threads:   (RAM budget,
//!         read, apron, LRU)
//!         stats)
//! ```
//!
//! - [`brick`]: what moves along the path — [`brick::BrickKey`] (level,
//!   channel, brick index; packs into a `u64`), [`brick::LoadedBrick`]
//!   (empty, constant or voxel data *with its apron*) and
//!   [`brick::BrickGeometry`] (the engine's brick grid over every level).
//! - [`loader`]: [`loader::Loader`], a pool of plain OS threads (not the
//!   compute pool: I/O must never block compute) that reads bricks from an
//!   OME-Zarr store on request, highest priority first. A brick whose padded
//!   region the store's per-brick statistics prove uniform is answered
//!   without reading voxels; other bricks are read with an apron of
//!   neighbouring voxels (clamped to the edge at the volume border), so that
//!   trilinear sampling inside a padded brick equals clamp-to-edge
//!   trilinear sampling of the whole level.
//! - [`host_cache`]: [`host_cache::HostCache`], the RAM cache of loaded
//!   bricks: a hard byte budget, LRU eviction, thread-safe.
//!
//! The virtual-memory manager (directory, page tables, brick pool, usage and
//! requests) is built on these in the same crate.
//!
//! [`bookkeeping`] holds the cache-management passes as plain functions:
//! what the virtual memory runs, and the CPU twins of the device kernels.
//!
//! This crate never depends on a GPU API. The loader and the session sit
//! behind the default feature `loader` (threads, files, HTTP); the rest
//! builds for `wasm32-unknown-unknown` without it.

pub mod assemble;
pub mod bookkeeping;
pub mod brick;
pub mod cells;
pub mod host_cache;
#[cfg(feature = "loader")]
pub mod loader;
pub mod ranges;
#[cfg(feature = "loader")]
pub mod session;
pub mod vm;
