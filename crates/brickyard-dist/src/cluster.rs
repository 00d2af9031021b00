//! The MPI glue (feature `mpi`): the processes `mpirun` started, as one
//! [`Team`] for the store's builder and with the exchanges the renderers
//! need (tiles on demand, images summed or composited).
//!
//! MPI is initialized only when an MPI launcher started this process
//! (OpenMPI's `OMPI_COMM_WORLD_SIZE`, PMI's `PMI_SIZE`, PMIx's
//! `PMIX_RANK`): a plain `brickyard …` never touches MPI. Only the main
//! thread calls MPI (`MPI_THREAD_FUNNELED`); rayon's threads never do.
//!
//! Failures are exchanged at meeting points ([`Team::agree`]): a rank that
//! fails says so at the next one, and every rank ends with the same error,
//! naming the rank and the cause. A rank that dies outright makes `mpirun`
//! end the job (non-zero exit); a conversion's output then stays
//! `OUT.partial`, which says it is incomplete.
//!
//! For tests, `BRICKYARD_MPI_FAIL=RANK:MEETING:error|exit` makes rank
//! `RANK` fail at its `MEETING`-th meeting point (1-based): `error` reports
//! an injected failure there, `exit` ends the process at once (status 3)
//! without a word to the others.

use brickyard_store::builder::Team;
use mpi::collective::SystemOperation;
use mpi::datatype::PartitionMut;
use mpi::topology::SimpleCommunicator;
use mpi::traits::*;
use mpi::Count;
use std::cell::Cell;

/// The ranks `mpirun` started.
pub struct Cluster {
    world: SimpleCommunicator,
    rank: usize,
    size: usize,
    meetings: Cell<u64>,
    fail: Option<(usize, u64, bool)>,
    // Dropped last: MPI_Finalize.
    _universe: mpi::environment::Universe,
}

// SAFETY: only the main thread calls MPI (the builder calls the `Team`
// methods from the thread that called it, which is the main thread); Sync
// is needed because the builder's context is shared with rayon's threads,
// which never call these methods.
unsafe impl Sync for Cluster {}

/// Whether an MPI launcher started this process.
pub fn launched() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK"]
        .iter()
        .any(|k| std::env::var_os(k).is_some())
}

impl Cluster {
    /// The ranks, when an MPI launcher started this process; `Ok(None)`
    /// otherwise.
    pub fn from_launcher() -> anyhow::Result<Option<Cluster>> {
        if !launched() {
            return Ok(None);
        }
        let (universe, _) = mpi::initialize_with_threading(mpi::Threading::Funneled)
            .ok_or_else(|| anyhow::anyhow!("MPI: MPI_Init failed or was called twice"))?;
        let world = universe.world();
        let fail = match std::env::var("BRICKYARD_MPI_FAIL") {
            Ok(v) => Some(parse_fail(&v)?),
            Err(_) => None,
        };
        Ok(Some(Cluster {
            rank: world.rank() as usize,
            size: world.size() as usize,
            world,
            meetings: Cell::new(0),
            fail,
            _universe: universe,
        }))
    }

    pub fn world(&self) -> &SimpleCommunicator {
        &self.world
    }

    /// Sum of `data` over all ranks into rank 0's `data`.
    pub fn sum_f32_to_root(&self, data: &mut [f32]) {
        let root = self.world.process_at_rank(0);
        // In pieces of 4 M values: bounded extra memory on rank 0.
        for chunk in data.chunks_mut(1 << 22) {
            if self.rank == 0 {
                let mut out = vec![0f32; chunk.len()];
                root.reduce_into_root(&chunk[..], &mut out[..], SystemOperation::sum());
                chunk.copy_from_slice(&out);
            } else {
                root.reduce_into(&chunk[..], SystemOperation::sum());
            }
        }
    }

    pub fn barrier(&self) {
        self.world.barrier();
    }
}

fn parse_fail(v: &str) -> anyhow::Result<(usize, u64, bool)> {
    let bad =
        || anyhow::anyhow!("BRICKYARD_MPI_FAIL: expected RANK:MEETING:error|exit, found {v:?}");
    let p: Vec<&str> = v.split(':').collect();
    if p.len() != 3 {
        return Err(bad());
    }
    let rank = p[0].parse().map_err(|_| bad())?;
    let meeting = p[1].parse().map_err(|_| bad())?;
    let exit = match p[2] {
        "exit" => true,
        "error" => false,
        _ => return Err(bad()),
    };
    Ok((rank, meeting, exit))
}

impl Team for Cluster {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.size
    }

    fn agree(&self, mine: Result<(), String>) -> Result<(), String> {
        let n = self.meetings.get() + 1;
        self.meetings.set(n);
        let mine = match self.fail {
            Some((r, m, exit)) if r == self.rank && m == n => {
                if exit {
                    std::process::exit(3);
                }
                mine.and(Err(format!(
                    "injected failure at meeting point {n} (BRICKYARD_MPI_FAIL)"
                )))
            }
            _ => mine,
        };
        let msg = match &mine {
            Ok(()) => vec![],
            Err(m) => format!("rank {}: {m}", self.rank).into_bytes(),
        };
        let len = msg.len() as Count;
        let mut lens = vec![0 as Count; self.size];
        self.world.all_gather_into(&len, &mut lens[..]);
        if lens.iter().all(|&l| l == 0) {
            return Ok(());
        }
        let displs: Vec<Count> = lens
            .iter()
            .scan(0, |a, &l| {
                let d = *a;
                *a += l;
                Some(d)
            })
            .collect();
        let mut all = vec![0u8; lens.iter().sum::<Count>() as usize];
        {
            let mut part = PartitionMut::new(&mut all[..], &lens[..], &displs[..]);
            self.world.all_gather_varcount_into(&msg[..], &mut part);
        }
        let text = String::from_utf8_lossy(&all);
        // The messages one after the other, in rank order.
        let mut out = vec![];
        let mut at = 0usize;
        for &l in &lens {
            if l > 0 {
                out.push(text[at..at + l as usize].to_string());
            }
            at += l as usize;
        }
        Err(out.join("; "))
    }

    fn broadcast(&self, words: &mut Vec<u64>) {
        let root = self.world.process_at_rank(0);
        let mut len = words.len() as u64;
        root.broadcast_into(&mut len);
        words.resize(len as usize, 0);
        root.broadcast_into(&mut words[..]);
    }

    fn or_to_root(&self, words: &mut [u64]) {
        let root = self.world.process_at_rank(0);
        if self.rank == 0 {
            let mut out = vec![0u64; words.len()];
            root.reduce_into_root(&words[..], &mut out[..], SystemOperation::bitwise_or());
            words.copy_from_slice(&out);
        } else {
            root.reduce_into(&words[..], SystemOperation::bitwise_or());
        }
    }

    fn sum_to_root(&self, words: &mut [u64]) {
        let root = self.world.process_at_rank(0);
        if self.rank == 0 {
            let mut out = vec![0u64; words.len()];
            root.reduce_into_root(&words[..], &mut out[..], SystemOperation::sum());
            words.copy_from_slice(&out);
        } else {
            root.reduce_into(&words[..], SystemOperation::sum());
        }
    }
}
