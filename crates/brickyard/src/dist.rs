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

/// How many processes an MPI launcher started with this one, from the
/// variables Open MPI (`OMPI_COMM_WORLD_SIZE`) and MPICH's Hydra or PMI
/// (`PMI_SIZE`) set; `None` when not under one.
#[cfg(not(feature = "mpi"))]
pub fn launcher_size() -> Option<usize> {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"]
        .iter()
        .find_map(|v| std::env::var(v).ok()?.trim().parse().ok())
}

/// Without the `mpi` feature: under `mpirun` with several processes each
/// would run the whole command alone (N renders of one image into one
/// file, N conversions racing for one lock), and `--distribute` shares
/// nothing: both are refused, saying how to build a binary that shares.
#[cfg(not(feature = "mpi"))]
pub fn refuse_launcher(cmd: &crate::Cmd) -> anyhow::Result<()> {
    const BUILD: &str = "cargo build --release -p brickyard --features brickyard/mpi";
    if let Some(n) = launcher_size().filter(|&n| n > 1) {
        anyhow::bail!(
            "started as one of {n} MPI processes, but this brickyard was built without MPI: each \
             would run the whole command alone. Run it without mpirun, or build it with MPI ({BUILD})"
        );
    }
    if let crate::Cmd::Render(r) = cmd {
        // (A value that is wrong is said as such first.)
        if let Some(d) = r
            .distribute
            .as_deref()
            .filter(|d| !matches!(*d, "image" | "data"))
        {
            anyhow::bail!("distribute: expected image or data, found {d:?}");
        }
        if r.distribute.is_some() {
            anyhow::bail!(
                "--distribute shares a render among the processes mpirun starts, but this \
                 brickyard was built without MPI ({BUILD})"
            );
        }
    }
    Ok(())
}
