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
//! without a word to the others. `MEETING` 0 is the start of the command,
//! before any meeting: `error` or `panic` there is that rank's own failure
//! (or panic), which the others do not hear of ([`Cluster::fail_alone`]).

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
    /// Ranks on this rank's node (sharing its memory), this one included.
    node_ranks: usize,
    meetings: Cell<u64>,
    fail: Option<(usize, u64, Fail)>,
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
        // The ranks that share this node's memory
        // (MPI_Comm_split_type(MPI_COMM_TYPE_SHARED)).
        let node_ranks = world.split_shared(world.rank()).size().max(1) as usize;
        Ok(Some(Cluster {
            rank: world.rank() as usize,
            size: world.size() as usize,
            node_ranks,
            world,
            meetings: Cell::new(0),
            fail,
            _universe: universe,
        }))
    }

    /// `BRICKYARD_MPI_FAIL=RANK:0:error|panic` for this rank: fail (or
    /// panic) at the start of the command, alone.
    pub fn fail_at_start(&self) -> anyhow::Result<()> {
        match self.fail {
            Some((r, 0, how)) if r == self.rank => match how {
                Fail::Panic => panic!("injected panic at the start (BRICKYARD_MPI_FAIL)"),
                _ => anyhow::bail!("injected failure at the start (BRICKYARD_MPI_FAIL)"),
            },
            _ => Ok(()),
        }
    }

    /// How many ranks run on this rank's node (this one included): they
    /// share its memory.
    pub fn ranks_on_node(&self) -> usize {
        self.node_ranks
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

    /// Every rank's `mine`, in rank order, on every rank (collective).
    pub fn all_gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>> {
        let len = mine.len() as Count;
        let mut lens = vec![0 as Count; self.size];
        self.world.all_gather_into(&len, &mut lens[..]);
        if lens.iter().all(|&l| l == 0) {
            return vec![vec![]; self.size];
        }
        let displs = displacements(&lens);
        let mut all = vec![0u8; lens.iter().sum::<Count>() as usize];
        {
            let mut part = PartitionMut::new(&mut all[..], &lens[..], &displs[..]);
            self.world.all_gather_varcount_into(mine, &mut part);
        }
        split_at_lens(&all, &lens)
    }

    /// Every rank's `mine`, in rank order, on rank 0; empty on the others
    /// (collective).
    pub fn gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>> {
        let root = self.world.process_at_rank(0);
        let len = mine.len() as Count;
        if self.rank != 0 {
            root.gather_into(&len);
            root.gather_varcount_into(mine);
            return vec![];
        }
        let mut lens = vec![0 as Count; self.size];
        root.gather_into_root(&len, &mut lens[..]);
        let displs = displacements(&lens);
        let mut all = vec![0u8; lens.iter().sum::<Count>() as usize];
        {
            let mut part = PartitionMut::new(&mut all[..], &lens[..], &displs[..]);
            root.gather_varcount_into_root(mine, &mut part);
        }
        split_at_lens(&all, &lens)
    }

    /// At the start of a command shared by the ranks: every rank must run
    /// the same command (`args`: its command line after the program's
    /// name) on the same inputs (`inputs`: each input's name and what this
    /// rank sees there, from [`input_identity`]). Ranks that differ (an
    /// MPMD job given different arguments, nodes that see different files
    /// at one path) would draw or write different things into one result,
    /// or wait for each other forever: the difference is an error every
    /// rank agrees on, naming the ranks (collective).
    pub fn check_same_command(
        &self,
        args: &[String],
        inputs: &[(String, String)],
    ) -> Result<(), String> {
        let mut mine = args.join("\u{1f}").into_bytes();
        mine.push(0);
        for (name, seen) in inputs {
            mine.extend_from_slice(format!("{name}\u{1f}{seen}\u{1e}").as_bytes());
        }
        let all = self.all_gather_bytes(&mine);
        let split = |m: &[u8]| -> (String, Vec<(String, String)>) {
            let t = String::from_utf8_lossy(m);
            let (a, i) = t.split_once('\0').unwrap_or((&t, ""));
            let inputs = i
                .split('\u{1e}')
                .filter(|x| !x.is_empty())
                .map(|x| {
                    let (n, s) = x.split_once('\u{1f}').unwrap_or((x, ""));
                    (n.to_string(), s.to_string())
                })
                .collect();
            (a.replace('\u{1f}', " "), inputs)
        };
        let ranks: Vec<_> = all.iter().map(|m| split(m)).collect();
        differences(&ranks)
    }

    /// This rank failed on its own (not at a meeting point: the error is
    /// not one every rank agreed on) while the others may be waiting for
    /// it in an exchange that will never complete. A polite end
    /// (`MPI_Finalize`) would wait for them forever; instead the failure
    /// goes to rank 0, which prints it once, and the job ends:
    ///
    /// - every rank failed so (the same check failed everywhere, before any
    ///   meeting): nobody waits in an exchange; rank 0 prints the
    ///   failures once (one message when all are the same) and this
    ///   returns on every rank, for a clean `MPI_Finalize` and a failure
    ///   status;
    /// - otherwise rank 0 (if it failed) or this rank prints the failure,
    ///   naming the rank, and calls `MPI_Abort`: `mpirun` ends every rank,
    ///   with a non-zero status.
    ///
    /// Returns (every rank failed alike) the failures as rank 0 says them
    /// (on rank 0; this rank's own on the others), for the caller to print
    /// once as an agreed error.
    pub fn fail_alone(&self, msg: &str) -> String {
        use std::time::{Duration, Instant};
        let tick = Duration::from_millis(10);
        let grace = |s: f64| Duration::from_secs_f64(s * grace_scale());
        if self.rank == 0 {
            let mut got: Vec<Option<String>> = vec![None; self.size];
            got[0] = Some(msg.to_string());
            let (t, mut n) = (Instant::now(), 1);
            while n < self.size && t.elapsed() < grace(ROOT_GRACE_S) {
                match self
                    .world
                    .any_process()
                    .immediate_matched_probe_with_tag(TAG_FAILED)
                {
                    Some(probed) => {
                        let (bytes, st) = probed.matched_receive_vec::<u8>();
                        let r = st.source_rank() as usize;
                        if got[r].is_none() {
                            n += 1;
                        }
                        got[r] = Some(String::from_utf8_lossy(&bytes).into_owned());
                    }
                    None => std::thread::sleep(tick),
                }
            }
            let text = failures_text(&got);
            if n == self.size {
                // Every rank is here, none in an exchange: end together.
                for r in 1..self.size {
                    self.world
                        .process_at_rank(r as i32)
                        .send_with_tag(&[1u8][..], TAG_RELEASED);
                }
                return text;
            }
            eprintln!("error: {text}");
            self.world.abort(1);
        }
        let mut bytes = msg.as_bytes().to_vec();
        bytes.truncate(MAX_FAILURE_BYTES);
        let root = self.world.process_at_rank(0);
        mpi::request::scope(|scope| {
            let mut req = Some(root.immediate_send_with_tag(scope, &bytes[..], TAG_FAILED));
            let t = Instant::now();
            loop {
                if let Some(probed) = root.immediate_matched_probe_with_tag(TAG_RELEASED) {
                    let _ = probed.matched_receive_vec::<u8>();
                    if let Some(r) = req.take() {
                        r.wait();
                    }
                    return msg.to_string();
                }
                if let Some(r) = req.take() {
                    if let Err(r) = r.test() {
                        req = Some(r);
                    }
                }
                if t.elapsed() > grace(OTHER_GRACE_S) {
                    // Rank 0 is not listening (it waits in an exchange):
                    // say it here, and end the job.
                    eprintln!("error: rank {}: {msg}", self.rank);
                    self.world.abort(1);
                }
                std::thread::sleep(tick);
            }
        })
    }
}

/// Message tags of [`Cluster::fail_alone`] (apart from the renderers').
const TAG_FAILED: i32 = 91;
const TAG_RELEASED: i32 = 92;
/// A failure's message as sent to rank 0 is cut at this length (a short
/// message goes out at once, whether or not rank 0 listens).
const MAX_FAILURE_BYTES: usize = 2000;
/// How long rank 0, failing alone, waits for the others' failures, and
/// how long another rank waits for rank 0 to end the job before it does.
const ROOT_GRACE_S: f64 = 2.0;
const OTHER_GRACE_S: f64 = 5.0;

/// `BRICKYARD_MPI_GRACE` scales the waits of [`Cluster::fail_alone`]
/// (tests; 1 by default).
fn grace_scale() -> f64 {
    std::env::var("BRICKYARD_MPI_GRACE")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v > 0.0)
        .unwrap_or(1.0)
}

/// Rank 0's report of the ranks' own failures (`None`: no word from that
/// rank): one message when every rank failed alike, else each naming its
/// rank.
fn failures_text(got: &[Option<String>]) -> String {
    if got.len() > 1 && got.iter().all(|m| m.is_some() && *m == got[0]) {
        return got[0].clone().unwrap_or_default();
    }
    got.iter()
        .enumerate()
        .filter_map(|(r, m)| m.as_ref().map(|m| format!("rank {r}: {m}")))
        .collect::<Vec<_>>()
        .join("; ")
}

/// What a rank sees at input path `path`, cheaply: a file's size and
/// modification time, a Zarr store's root metadata (hashed), a folder's
/// count of entries; or that it sees nothing there. Paths that name a
/// server (`s3://`, `http://`…) are the server's: an empty identity.
pub fn input_identity(path: &std::path::Path) -> String {
    let s = path.to_string_lossy();
    if s.contains("://") {
        return String::new();
    }
    let md = match std::fs::metadata(path) {
        Ok(m) => m,
        Err(e) => return format!("nothing readable ({e})"),
    };
    if md.is_dir() {
        for name in ["zarr.json", ".zattrs", ".zgroup", ".zarray"] {
            if let Ok(b) = std::fs::read(path.join(name)) {
                return format!("a store whose {name} hashes to {:016x}", content_hash(&b));
            }
        }
        let n = std::fs::read_dir(path).map(|d| d.count()).unwrap_or(0);
        return format!("a folder of {n} entries");
    }
    let mtime = md
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_secs());
    format!("{} bytes modified at {mtime} s (Unix time)", md.len())
}

/// A hash of `b` that every rank computes alike (the same binary: std's
/// default hasher with its fixed keys).
fn content_hash(b: &[u8]) -> u64 {
    use std::hash::Hasher;
    let mut h = std::hash::DefaultHasher::new();
    h.write(b);
    h.finish()
}

/// The ranks' command lines and inputs (in rank order) that differ from
/// rank 0's, said in words; `Ok` when all are the same.
fn differences(ranks: &[(String, Vec<(String, String)>)]) -> Result<(), String> {
    let list = |rs: &[usize]| match rs {
        [r] => format!("rank {r}"),
        _ => format!(
            "ranks {}",
            rs.iter()
                .map(|r| r.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    // Groups of ranks with the same command line, in order of first rank.
    let mut groups: Vec<(String, Vec<usize>)> = vec![];
    for (r, (a, _)) in ranks.iter().enumerate() {
        match groups.iter_mut().find(|g| g.0 == *a) {
            Some(g) => g.1.push(r),
            None => groups.push((a.clone(), vec![r])),
        }
    }
    if groups.len() > 1 {
        let said: Vec<String> = groups
            .iter()
            .map(|(a, rs)| format!("{} ran `{a}`", list(rs)))
            .collect();
        return Err(format!(
            "the ranks were not given the same command: {}; every rank of a shared command \
             must be given the same arguments",
            said.join(", ")
        ));
    }
    let inputs = &ranks[0].1;
    for (i, (name, _)) in inputs.iter().enumerate() {
        let mut groups: Vec<(String, Vec<usize>)> = vec![];
        for (r, (_, seen)) in ranks.iter().enumerate() {
            let s = seen.get(i).map(|x| x.1.clone()).unwrap_or_default();
            match groups.iter_mut().find(|g| g.0 == s) {
                Some(g) => g.1.push(r),
                None => groups.push((s, vec![r])),
            }
        }
        if groups.len() > 1 {
            let said: Vec<String> = groups
                .iter()
                .map(|(s, rs)| {
                    format!(
                        "{} {} {s}",
                        list(rs),
                        ["see", "sees"][(rs.len() == 1) as usize]
                    )
                })
                .collect();
            return Err(format!(
                "{name}: the ranks do not see the same input there: {}; every rank must read \
                 the same data (a folder all nodes share)",
                said.join(", ")
            ));
        }
    }
    Ok(())
}

fn displacements(lens: &[Count]) -> Vec<Count> {
    lens.iter()
        .scan(0, |a, &l| {
            let d = *a;
            *a += l;
            Some(d)
        })
        .collect()
}

fn split_at_lens(all: &[u8], lens: &[Count]) -> Vec<Vec<u8>> {
    let mut out = vec![];
    let mut at = 0usize;
    for &l in lens {
        out.push(all[at..at + l as usize].to_vec());
        at += l as usize;
    }
    out
}

/// What `BRICKYARD_MPI_FAIL` makes a rank do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fail {
    Error,
    Exit,
    Panic,
}

fn parse_fail(v: &str) -> anyhow::Result<(usize, u64, Fail)> {
    let bad = || {
        anyhow::anyhow!(
            "BRICKYARD_MPI_FAIL: expected RANK:MEETING:error|exit (or RANK:0:error|panic), found {v:?}"
        )
    };
    let p: Vec<&str> = v.split(':').collect();
    if p.len() != 3 {
        return Err(bad());
    }
    let rank = p[0].parse().map_err(|_| bad())?;
    let meeting = p[1].parse().map_err(|_| bad())?;
    let how = match p[2] {
        "exit" if meeting > 0 => Fail::Exit,
        "error" => Fail::Error,
        "panic" if meeting == 0 => Fail::Panic,
        _ => return Err(bad()),
    };
    Ok((rank, meeting, how))
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
            Some((r, m, how)) if r == self.rank && m == n => {
                if how == Fail::Exit {
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
        let all = self.all_gather_bytes(&msg);
        if all.iter().all(|m| m.is_empty()) {
            return Ok(());
        }
        // The messages one after the other, in rank order.
        let out: Vec<String> = all
            .iter()
            .filter(|m| !m.is_empty())
            .map(|m| String::from_utf8_lossy(m).into_owned())
            .collect();
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
