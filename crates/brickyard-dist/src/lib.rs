//! Work shared by several processes: distributed conversion, image- and
//! data-parallel rendering, sort-last compositing.
//!
//! The bands of image-parallel renders ([`bands`]), the k-d split of the bricks into convex
//! regions with their visibility order ([`kd`]) and the compositing of
//! premultiplied RGBA with its exchange schedules ([`composite`]) are plain
//! code, tested in one process. The MPI glue ([`cluster`]) sits behind the
//! `mpi` feature.

pub mod bands;
#[cfg(feature = "mpi")]
pub mod cluster;
pub mod composite;
pub mod kd;
#[cfg(feature = "mpi")]
pub use cluster::Cluster;
#[cfg(feature = "mpi")]
pub mod share;

pub use brickyard_run::share::Agreed;
