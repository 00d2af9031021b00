//! Work shared by several processes: distributed conversion, image- and
//! data-parallel rendering, sort-last compositing.
//!
//! The scheduling ([`tiles`]), the k-d split of the bricks into convex
//! regions with their visibility order ([`kd`]) and the compositing of
//! premultiplied RGBA with its exchange schedules ([`composite`]) are plain
//! code, tested in one process. The MPI glue ([`cluster`]) sits behind the
//! `mpi` feature.

#[cfg(feature = "mpi")]
pub mod cluster;
pub mod composite;
pub mod kd;
#[cfg(feature = "mpi")]
pub use cluster::Cluster;

/// A failure every rank agreed on at a meeting point (the message names
/// the rank that failed and why).
#[derive(Debug, Clone)]
pub struct Agreed(pub String);

impl std::fmt::Display for Agreed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Agreed {}
