//! The processes `mpirun` started, as the commands see them: with the
//! `mpi` feature the MPI ranks ([`brickyard_dist::Cluster`]); without it,
//! a type with no values (every command runs alone).

#[cfg(feature = "mpi")]
pub use brickyard_dist::Cluster;

/// Without the `mpi` feature there are no ranks to share work with.
#[cfg(not(feature = "mpi"))]
pub enum Cluster {}

/// Rank and count of the ranks (`(0, 1)` alone).
pub fn rank_size(c: Option<&Cluster>) -> (usize, usize) {
    match c {
        #[cfg(feature = "mpi")]
        Some(c) => {
            use brickyard_store::builder::Team;
            (c.rank(), c.size())
        }
        #[cfg(not(feature = "mpi"))]
        Some(c) => match *c {},
        None => (0, 1),
    }
}

/// Whether an error is one every rank agreed on (rank 0 prints it; the
/// others only exit with a failure status).
pub fn agreed(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        matches!(
            c.downcast_ref::<brickyard_store::StoreError>(),
            Some(brickyard_store::StoreError::Team(_))
        ) || c.downcast_ref::<brickyard_run::share::Agreed>().is_some()
    })
}
