//! One memory budget for the whole process (`--memory`): the brick pool,
//! the host cache, the loader's decoded-chunk caches and the image buffers
//! are split out of it, after a fixed allowance for the program itself.

use anyhow::{bail, Context, Result};
use brickyard_store::info::human_bytes;

/// The program itself: code, allocator, thread stacks (rayon, loader),
/// codec buffers, request collectors and the store's metadata.
pub const FIXED_BYTES: u64 = 48 << 20;

/// Bytes of image buffers per pixel of a render: the frame (RGBA f32)
/// twice (the one drawn and the last kept), the request pass (at most a
/// quarter),
/// and the 8-bit copy written to PNG.
pub const IMAGE_BYTES_PER_PIXEL: u64 = 16 * 2 + 4 + 4;

/// The viewer's window beyond [`FIXED_BYTES`]: the windowing and OpenGL
/// libraries (a software OpenGL included), egui, and the views' textures.
pub const WINDOW_BYTES: u64 = 96 << 20;

/// What a hardware device back end adds to the process beyond
/// [`FIXED_BYTES`]: the driver's libraries, its shader compiler at work,
/// staging and readback buffers (a hardware driver compiles the render
/// kernel on the device's own compiler; its host share was not measured
/// here, for want of such a device).
pub const DEVICE_BYTES: u64 = 192 << 20;

/// Bricks a device back end writes into its pool per frame at most. They
/// go through one staging buffer, host memory on every device, whose rows
/// start 256 bytes apart: for 32³ bricks of 4-byte voxels (136-byte rows
/// of padded bricks) nearly twice the bricks' bytes. Twice this is set
/// aside besides the driver's share ([`DEVICE_BYTES`],
/// [`SOFTWARE_DEVICE_BYTES`]); a pool larger than it fills over several
/// frames.
pub const STAGING_BYTES: u64 = 32 << 20;

/// The same for a software adapter (Mesa's lavapipe), whose compiler is
/// LLVM in this process: a 256² render of a 7.5 MiB store with a 16 MiB
/// pool and the shader cache empty (`MESA_SHADER_CACHE_DISABLE=true`, as
/// on a fresh machine) peaked at 481 MiB against the CPU back end's 64 MiB:
/// 401 MiB for the driver beside the pool's copy (168 MiB more than the
/// CPU back end with the cache warm). A software adapter's device memory
/// (the pool's copy) is host memory besides, counted apart.
pub const SOFTWARE_DEVICE_BYTES: u64 = 448 << 20;

/// Physical memory (from /proc/meminfo; 8 GiB where unknown).
pub fn physical_ram() -> u64 {
    known_ram().unwrap_or(8 << 30)
}

/// Physical memory, where /proc/meminfo tells it.
fn known_ram() -> Option<u64> {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|k| k.parse::<u64>().ok())
        })
        .map(|kib| kib << 10)
}

/// The default budget: a quarter of physical memory, or of the memory
/// limit of the process's control group where that is lower, and within
/// what its address-space limit (`ulimit -v`) leaves beside the program
/// ([`default_memory_source`] says which).
pub fn default_memory() -> u64 {
    default_memory_source().0
}

/// Processes of one job on this node (MPI ranks), which share its memory:
/// the default budget is divided among them (1: this process alone).
static NODE_PROCESSES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// Divide the default budget among the `n` processes of one job that run
/// on this node (an explicit `--memory` stays each one's).
pub fn share_default_among(n: usize) {
    NODE_PROCESSES.store(n.max(1) as u64, std::sync::atomic::Ordering::Relaxed);
}

fn node_processes() -> u64 {
    NODE_PROCESSES.load(std::sync::atomic::Ordering::Relaxed)
}

/// What the program maps beside its budget (its code, thread stacks, the
/// allocator's spare room), for the address-space limit: `render` at
/// `--memory 256MiB` ran within `ulimit -v 400000` (390 MiB).
const ADDRESS_SPACE_BESIDE: u64 = 192 << 20;

/// [`default_memory`], and what it is a share of: "RAM", "the control
/// group's memory limit" or "the address-space limit".
pub fn default_memory_source() -> (u64, &'static str) {
    let ram = physical_ram();
    let (mut m, mut of) = match cgroup_limit() {
        Some(c) if c < ram => (c / 4, "the control group's memory limit"),
        _ => (ram / 4, "RAM"),
    };
    // (The address-space limit is each process's own.)
    m /= node_processes();
    if let Some(a) = address_space_limit() {
        let within = a.saturating_sub(ADDRESS_SPACE_BESIDE);
        if within < m {
            (m, of) = (within.max(16 << 20), "the address-space limit");
        }
    }
    (m, of)
}

/// The process's address-space limit (`RLIMIT_AS`, `ulimit -v`), unless
/// unlimited.
pub fn address_space_limit() -> Option<u64> {
    let mut r = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct it is given.
    let ok = unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut r) } == 0;
    (ok && r.rlim_cur != libc::RLIM_INFINITY).then_some(r.rlim_cur)
}

/// The memory limit of the process's control group (v2 `memory.max` of
/// its group and those above it, or v1 `memory.limit_in_bytes`), unless
/// there is none.
fn cgroup_limit() -> Option<u64> {
    let groups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let read = |f: &std::path::Path| -> Option<u64> {
        let t = std::fs::read_to_string(f).ok()?;
        let v = t.trim().parse::<u64>().ok()?;
        // ("max" in v2; v1 says "none" with a page-rounded i64::MAX.)
        (v < 1 << 60).then_some(v)
    };
    let mut least: Option<u64> = None;
    let mut take = |v: Option<u64>| {
        if let Some(v) = v {
            least = Some(least.map_or(v, |l| l.min(v)));
        }
    };
    for line in groups.lines() {
        let mut parts = line.splitn(3, ':');
        let (_, ctrl, path) = (parts.next()?, parts.next()?, parts.next()?);
        let path = path.trim_start_matches('/');
        if ctrl.is_empty() {
            // v2: the group and every group above it.
            let mut dir = std::path::Path::new("/sys/fs/cgroup").join(path);
            loop {
                take(read(&dir.join("memory.max")));
                if !dir.pop() || !dir.starts_with("/sys/fs/cgroup") {
                    break;
                }
            }
        } else if ctrl.split(',').any(|c| c == "memory") {
            let root = std::path::Path::new("/sys/fs/cgroup/memory");
            take(read(&root.join(path).join("memory.limit_in_bytes")));
            // (Inside a container the group's own folder is the root.)
            take(read(&root.join("memory.limit_in_bytes")));
        }
    }
    least
}

/// The process's peak resident set so far (VmHWM), where the system says.
pub fn peak_rss() -> Option<u64> {
    status_bytes("VmHWM:")
}

/// The budget [`relieve`] keeps the resident set under (0: none).
static WATCHED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// What the process held when [`watch`] was called beyond the program's
/// own allowance ([`FIXED_BYTES`]): someone else's memory (a Python
/// session's arrays), which [`relieve`] does not count against the budget
/// (with a 1 GiB array held, a 256 MiB render trimmed at every brick and
/// took a fifth longer).
static BESIDE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Have [`relieve`] keep the resident set within `total` bytes, between
/// frames and while the loader's threads load ([`relieve_while_loading`]).
pub fn watch(total: u64) {
    WATCHED.store(total, std::sync::atomic::Ordering::Relaxed);
    BESIDE.store(
        rss().unwrap_or(0).saturating_sub(FIXED_BYTES),
        std::sync::atomic::Ordering::Relaxed,
    );
    brickyard_cache::loader::set_relief(relieve_while_loading);
}

/// [`relieve`] from the loader's threads, after each brick they load, at
/// most every 10 ms (reading the resident set costs tens of µs). Between
/// frames alone was too late: a batch render's frame waits for all its
/// bricks, and the heaps grew meanwhile. 512² DVR of 512³ 32-bit labels
/// at `--memory 256MiB`, four runs each: 252–272 MiB with 2 loader
/// threads and 271–282 MiB with 4 before, 232–251 and 241–259 MiB with
/// this, in the same time (1.5–1.9 s).
pub fn relieve_while_loading() {
    use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
    static LAST: AtomicU64 = AtomicU64::new(0);
    static START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    let now = START
        .get_or_init(std::time::Instant::now)
        .elapsed()
        .as_millis() as u64
        + 10;
    let last = LAST.load(Relaxed);
    if now < last + 10 || LAST.compare_exchange(last, now, Relaxed, Relaxed).is_err() {
        return;
    }
    relieve();
}

/// Between frames: where the resident set has come within a tenth of the
/// watched budget, give the memory the allocator keeps freed back to the
/// system. The shares are counted by what they hold; the allocator keeps
/// what bricks and chunks let go of in the heaps of the threads that made
/// them, for the next of their size ([`SLACK`] is set aside for it), and
/// a render of 32-bit labels went 23–31 MiB past a 256 MiB budget so
/// before either. Far from the budget nothing is done:
/// memory kept for reuse spares fresh pages, which cost more than the
/// reads (BENCHMARKS.md, "What a first fill's fresh memory costs").
pub fn relieve() {
    use std::sync::atomic::Ordering::Relaxed;
    let b = WATCHED.load(Relaxed);
    let beside = BESIDE.load(Relaxed);
    if b > 0 && rss().is_some_and(|r| r.saturating_sub(beside) > b - b / 10) {
        crate::window::give_back_freed_memory();
    }
}

/// The process's resident set now (VmRSS), where the system says.
pub fn rss() -> Option<u64> {
    status_bytes("VmRSS:")
}

fn status_bytes(key: &str) -> Option<u64> {
    let t = std::fs::read_to_string("/proc/self/status").ok()?;
    let l = t.lines().find(|l| l.starts_with(key))?;
    l.split_whitespace()
        .nth(1)?
        .parse::<u64>()
        .ok()
        .map(|k| k << 10)
}

/// The allocator's slack beside the host cache and the decoded chunks:
/// an eighth of their bytes. Measured on a render of 32-bit labels whose
/// view did not fit its pool (512³, 512², CPU; BENCHMARKS.md): at
/// `--memory` 128/192/256 MiB it peaked at 126–138/194–211/266–281 MiB
/// before, 120–124/185–188/262–268 MiB with this slack and freed memory
/// given back between frames ([`relieve`]): under the first two budgets,
/// still up to 5 % past the third (the heaps grow within one frame; see
/// [`relieve_while_loading`] for what holds them now).
const SLACK: u64 = 8;

/// The least host cache a split keeps.
pub const HOST_LEAST: u64 = 1 << 20;

/// How a budget is split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Split {
    pub total: u64,
    pub pool: u64,
    pub host: u64,
    /// The loader's decoded-chunk caches (all levels).
    pub chunks: u64,
    pub images: u64,
    pub fixed: u64,
    /// The device back end's share (its driver, and on a software adapter
    /// its memory); part of `fixed`.
    pub device: u64,
    /// The filters of a live derived channel (`--derive`): the most their
    /// blocks hold at once.
    pub filters: u64,
    /// The samples a progressive render keeps (`--progressive`).
    pub samples: u64,
    /// Whether the total was given (`--memory`) rather than the default.
    pub explicit: bool,
}

impl Split {
    /// Where the pool, a share of the budget, is too small to keep the
    /// coarsest level resident (`least` bytes of pool: see
    /// `BrickGeometry::pinned_levels`), it takes what it lacks from the
    /// host cache's share, which keeps [`HOST_LEAST`] (a host cache
    /// smaller than the coarsest level still pins it: the bricks go
    /// straight on into the pool; a 256² render of 32-bit labels with 128
    /// KiB of host cache completed as with 8 MiB). Returns the bytes
    /// moved; `None` where the host cache cannot spare them (or the pool
    /// needs none).
    pub fn lend_pool(&mut self, least: u64) -> Option<u64> {
        let short = least.checked_sub(self.pool).filter(|s| *s > 0)?;
        if self.host < HOST_LEAST.saturating_add(short) {
            return None;
        }
        self.host -= short;
        self.pool += short;
        Some(short)
    }

    /// A total that gives the pool `least` bytes, the host cache lending
    /// what it can spare ([`Split::lend_pool`]), in whole MiB: what they
    /// lack twice over, as at most half of a raise reaches the pool and
    /// the host cache together (the decoded chunks, the allocator's slack
    /// and a derived channel's filters take their parts of it).
    pub fn total_holding_pool(&self, least: u64) -> u64 {
        let short = least.saturating_sub(self.pool);
        let spare = self.host.saturating_sub(HOST_LEAST);
        let more = short.saturating_sub(spare).saturating_mul(2);
        self.total.saturating_add(more).div_ceil(1 << 20) << 20
    }

    pub fn describe(&self) -> String {
        format!(
            "memory budget {}{}: pool {}, host cache {}, decoded chunks {}, images {}, {}{}program {}",
            human_bytes(self.total),
            if self.explicit {
                String::new()
            } else {
                let among = match node_processes() {
                    1 => String::new(),
                    n => format!(", divided among the {n} ranks on this node"),
                };
                match default_memory_source().1 {
                    "RAM" => format!(" (default: a quarter of RAM{among})"),
                    "the address-space limit" => {
                        " (default: within the address-space limit, ulimit -v)".to_string()
                    }
                    of => format!(" (default: a quarter of {of}{among})"),
                }
            },
            human_bytes(self.pool),
            human_bytes(self.host),
            human_bytes(self.chunks),
            human_bytes(self.images),
            if self.filters > 0 {
                format!("derived channel's filters {}, ", human_bytes(self.filters))
            } else {
                String::new()
            }
                + &if self.samples > 0 {
                    format!("kept samples {}, ", human_bytes(self.samples))
                } else {
                    String::new()
                },
            if self.device > 0 {
                format!("device back end {}, ", human_bytes(self.device))
            } else {
                String::new()
            },
            human_bytes(self.fixed - self.device)
        )
    }
}

/// Split `total` (default: [`default_memory`]) for images of `pixels`
/// pixels and a store of `levels` levels; `pool` and `host` override
/// their shares. A split that does not fit an explicit total is refused.
pub fn split(
    total: Option<u64>,
    pool: Option<u64>,
    host: Option<u64>,
    pixels: u64,
    levels: usize,
) -> Result<Split> {
    split_with(total, pool, host, pixels, levels, 0)
}

/// [`split`] for a program that needs `extra` bytes beyond
/// [`FIXED_BYTES`] for itself (the viewer's window: see [`WINDOW_BYTES`]).
pub fn split_with(
    total: Option<u64>,
    pool: Option<u64>,
    host: Option<u64>,
    pixels: u64,
    levels: usize,
    extra: u64,
) -> Result<Split> {
    split_with_shares(total, pool, host, pixels, levels, extra, (0, 0))
}

/// [`split_with`] with shares set aside before the pool and host cache
/// take theirs: `filters` bytes for the filters of a live derived channel
/// (see [`crate::derive::Derived::within`]) and `samples` bytes for the
/// samples a progressive render keeps.
pub fn split_with_shares(
    total: Option<u64>,
    pool: Option<u64>,
    host: Option<u64>,
    pixels: u64,
    levels: usize,
    extra: u64,
    (filters, samples): (u64, u64),
) -> Result<Split> {
    if pool == Some(0) {
        bail!("pool: expected a size above 0 (e.g. 256MiB)");
    }
    if host == Some(0) {
        bail!("host: expected a size above 0 (e.g. 256MiB)");
    }
    let images = pixels.saturating_mul(IMAGE_BYTES_PER_PIXEL);
    let shares_given = pool.is_some() || host.is_some();
    // Each level's chunk cache keeps at least half a MiB.
    let fixed = FIXED_BYTES + extra + levels as u64 * (512 << 10);
    let explicit = total.is_some();
    let want_total = total.unwrap_or_else(default_memory);
    // (Sums saturate: a size given as 2^64 − 1 bytes is refused below as
    // more than the machine has, not wrapped around to a small one.)
    let aside = filters.saturating_add(samples);
    let rest = want_total.saturating_sub(fixed.saturating_add(images).saturating_add(aside));
    let min_chunks = 4u64 << 20;
    // The host cache and the decoded chunks turn over as bricks come and
    // go, and the allocator keeps part of what they free in its heaps
    // (a freed chunk's room is not always the shape the next allocation
    // needs): [`SLACK`] of their bytes is set aside for it, out of the
    // rest where their shares are computed, beside them where given.
    let slack = |host: u64, chunks: u64| host.saturating_add(chunks) / SLACK;
    let less = |x: u64| x - x / (SLACK + 1);
    let (pool_given, host_given) = (pool, host);
    let (pool, host, chunks, held) = match (pool, host) {
        (None, None) => {
            let chunks = (rest * 15 / 100).min(256 << 20);
            let pool = (rest - chunks) * 55 / 100;
            let (h, c) = (less(rest - chunks - pool), less(chunks));
            (pool, h, c, rest - chunks - pool - h + chunks - c)
        }
        (Some(p), None) => {
            let left = rest.saturating_sub(p);
            let chunks = (left / 4).clamp(min_chunks, 256 << 20);
            let h0 = left.saturating_sub(chunks);
            let (h, c) = (less(h0), less(chunks).max(min_chunks.min(chunks)));
            (p, h, c, h0 - h + chunks - c)
        }
        (None, Some(h)) => {
            let left = rest.saturating_sub(h);
            let chunks = (left / 4).clamp(min_chunks, 256 << 20);
            let s = slack(h, chunks);
            (left.saturating_sub(chunks).saturating_sub(s), h, chunks, s)
        }
        (Some(p), Some(h)) => {
            let left = rest.saturating_sub(p.saturating_add(h));
            let chunks = left.clamp(min_chunks, 256 << 20);
            let s = slack(h, chunks);
            let chunks = if left >= min_chunks + s {
                left - s
            } else {
                chunks
            };
            (p, h, chunks.clamp(min_chunks, 256 << 20), s)
        }
    };
    let program = fixed;
    let fixed = fixed.saturating_add(held);
    let need = [pool, host, chunks, images, fixed, aside]
        .into_iter()
        .fold(0u64, u64::saturating_add);
    if explicit && (need > want_total || pool == 0 || host == 0) {
        // The least total this split holds: the shares given (or a few
        // MiB each), the decoded chunks' least and their slack (of the
        // chunks' share with its slack in it: 1/7 of host and chunks), and
        // the rest as counted here (what the pool's pinned levels need is
        // checked apart, saying so).
        let (p, h) = (pool_given.unwrap_or(4 << 20), host_given.unwrap_or(4 << 20));
        let slack_most = h.saturating_add(min_chunks) / (SLACK - 1) + 1;
        let least = [p, h, min_chunks, slack_most, images, program, aside]
            .into_iter()
            .fold(0u64, u64::saturating_add);
        let least = least.div_ceil(1 << 20) << 20;
        // More than the machine has: no --memory holds it.
        if let Some(ram) = known_ram().filter(|r| least > *r) {
            bail!(
                "memory: {} does not hold this split, nor would any --memory on this machine \
                 ({} of RAM): images {}{} and {} for the program need {} at least; {}",
                human_bytes(want_total),
                human_bytes(ram),
                human_bytes(images),
                if aside > 0 {
                    format!(", set aside {}", human_bytes(aside))
                } else {
                    String::new()
                },
                human_bytes(program),
                human_bytes(least),
                if images > least / 2 {
                    "draw a smaller image (or fewer views)"
                } else if shares_given {
                    "lower --pool/--host"
                } else {
                    "draw a smaller image"
                }
            );
        }
        bail!(
            "memory: {} does not hold this split: pool {}, host cache {}, decoded chunks {} (at least {}), images {}{} and {} for the program; raise --memory ({}MiB holds it){}{}",
            human_bytes(want_total),
            human_bytes(pool),
            human_bytes(host),
            human_bytes(chunks),
            human_bytes(min_chunks),
            human_bytes(images),
            if filters > 0 {
                format!(", the derived channel's filters {}", human_bytes(filters))
            } else {
                String::new()
            } + &if samples > 0 {
                format!(", the kept samples {}", human_bytes(samples))
            } else {
                String::new()
            },
            human_bytes(fixed),
            least >> 20,
            if shares_given { " or lower --pool/--host" } else { "" },
            if images > least / 8 { " or draw a smaller image" } else { "" }
        );
    }
    // Without --memory, explicit pool and host sizes stand; the total is
    // what they add up to.
    let total = want_total.max(need);
    if let Some(ram) = known_ram().filter(|r| total > *r) {
        // (The default budget is within RAM: without shares given, what
        // passes it is the images, the rest being fixed.)
        if !shares_given && !explicit {
            bail!(
                "memory: the images take {} (and the rest {}), but this machine has {} of RAM; \
                 draw a smaller image or fewer views",
                human_bytes(images),
                human_bytes(total.saturating_sub(images)),
                human_bytes(ram)
            );
        }
        bail!(
            "memory: pool {}, host cache {} and the rest need {}, but this machine has {} of RAM; lower {}",
            human_bytes(pool),
            human_bytes(host),
            human_bytes(total),
            human_bytes(ram),
            match (shares_given, explicit) {
                (true, true) => "--pool/--host or --memory",
                (true, false) => "--pool/--host",
                _ => "--memory",
            }
        );
    }
    if pool == 0 {
        bail!("memory: no room left for the brick pool; raise --memory or set --pool");
    }
    Ok(Split {
        total,
        pool,
        host: host.max(HOST_LEAST),
        chunks,
        images,
        fixed,
        device: 0,
        filters,
        samples,
        explicit,
    })
}

/// Parse `1GiB`, `512MiB`, `2G`, `100MB`, `4096`.
pub fn parse_bytes(s: &str) -> Result<u64> {
    let t = s.trim();
    let idx = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(idx);
    let v: f64 = num
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite())
        .with_context(|| {
            format!("expected a size like 512MiB, 2GiB or 4096 (bytes), found {s:?}")
        })?;
    if matches!(unit.trim().to_ascii_lowercase().as_str(), "" | "b") && v.fract() != 0.0 {
        bail!("expected a whole number of bytes, found {s:?} (or a unit: 1.5GiB)");
    }
    let mul: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kib" => 1024.0,
        "kb" => 1e3,
        "m" | "mib" => 1024.0 * 1024.0,
        "mb" => 1e6,
        "g" | "gib" => 1024.0 * 1024.0 * 1024.0,
        "gb" => 1e9,
        "t" | "tib" => 1024f64.powi(4),
        "tb" => 1e12,
        u => {
            bail!("unknown unit {u:?} in {s:?}; expected B, KiB, MiB, GiB, TiB (or KB, MB, GB, TB)")
        }
    };
    let bytes = v * mul;
    if bytes >= u64::MAX as f64 {
        bail!("{s:?} is more than 16 EiB (2^64 bytes); expected a size like 512MiB or 2GiB");
    }
    Ok(bytes as u64)
}

#[cfg(test)]
mod tests {

    /// Images larger than the machine's RAM: no --memory is asked for,
    /// given or not; the image's size is named as what to change.
    #[test]
    fn images_past_the_machines_ram_ask_for_a_smaller_image() {
        let Some(ram) = known_ram() else { return };
        let pixels = ram / IMAGE_BYTES_PER_PIXEL * 2;
        let e = split(None, None, None, pixels, 4).unwrap_err().to_string();
        assert!(
            e.contains("the images take") && e.contains("draw a smaller image or fewer views"),
            "{e}"
        );
        let e = split(Some(ram / 2), None, None, pixels, 4)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("nor would any --memory on this machine")
                && e.contains("draw a smaller image"),
            "{e}"
        );
        assert!(!e.contains("raise --memory"), "{e}");
    }

    #[test]
    fn the_host_cache_lends_the_pool_what_it_can_spare() {
        let mb = |x: u64| x << 20;
        let base = Split {
            total: mb(64),
            pool: mb(2),
            host: mb(2),
            chunks: mb(1),
            images: mb(1),
            fixed: mb(50),
            device: 0,
            filters: 0,
            samples: 0,
            explicit: true,
        };
        // Short by 1 MiB, the host cache keeps its least.
        let mut s = base;
        assert_eq!(s.lend_pool(mb(3)), Some(mb(1)));
        assert_eq!((s.pool, s.host), (mb(3), HOST_LEAST));
        assert_eq!(s.pool + s.host, base.pool + base.host);
        // Short by more than it can spare: unchanged, and the total named
        // gives twice what was missing beyond the spare.
        let mut s = base;
        assert_eq!(s.lend_pool(mb(4)), None);
        assert_eq!(s, base);
        assert_eq!(s.total_holding_pool(mb(4)), mb(66));
        // A pool that holds it already borrows nothing.
        assert_eq!(s.lend_pool(mb(2)), None);
        assert_eq!(s.total_holding_pool(mb(2)), mb(64));
    }
    use super::*;

    /// A split --memory cannot hold names the least it can, and that much
    /// holds it (given shares or not, with images, levels, the program's
    /// extra and the set-aside shares).
    #[test]
    fn a_refused_split_names_a_total_that_holds_it() {
        let mib = 1u64 << 20;
        let mut tried = 0;
        for (pool, host) in [
            (None, None),
            (Some(64 * mib), None),
            (None, Some(64 * mib)),
            (Some(64 * mib), Some(64 * mib)),
            (Some(300 * mib), Some(5 * mib)),
            (Some(mib), Some(200 * mib)),
        ] {
            for (pixels, levels, extra, shares) in [
                (0, 1, 0, (0, 0)),
                (1 << 20, 5, 160 * mib, (0, 0)),
                (640 * 480, 9, 7 * mib + 12345, (30 * mib, 20 * mib)),
            ] {
                let e = split_with_shares(Some(8 * mib), pool, host, pixels, levels, extra, shares)
                    .unwrap_err()
                    .to_string();
                let figure: u64 = e
                    .split("raise --memory (")
                    .nth(1)
                    .and_then(|t| t.split("MiB holds it)").next())
                    .and_then(|n| n.parse().ok())
                    .unwrap_or_else(|| panic!("no figure in {e}"));
                let at =
                    |t: u64| split_with_shares(Some(t), pool, host, pixels, levels, extra, shares);
                let s = at(figure * mib).unwrap_or_else(|e| {
                    panic!("{pool:?} {host:?} {pixels} {levels} {extra}: {figure} MiB: {e}")
                });
                assert!(s.pool > 0 && s.host > 0 && s.total <= figure * mib);
                // Not far above the least that holds it (the shares not
                // given are counted at 4 MiB each).
                assert!(at((figure - 16) * mib).is_err(), "{e}");
                tried += 1;
            }
        }
        assert_eq!(tried, 18);
    }

    #[test]
    fn shares_add_up_to_the_budget() {
        let s = split(Some(1 << 30), None, None, 1 << 20, 5).unwrap();
        assert_eq!(s.pool + s.host + s.chunks + s.images + s.fixed, s.total);
        assert!(s.pool > s.host / 2 && s.host > 0 && s.chunks >= 4 << 20);
        assert_eq!(s.images, 40 << 20);
    }

    #[test]
    fn overrides_that_do_not_fit_are_refused() {
        let e = split(
            Some(256 << 20),
            Some(200 << 20),
            Some(100 << 20),
            1 << 20,
            5,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("does not hold"), "{e}");
        // Without --memory they stand, and the total grows to hold them.
        let s = split(None, Some(1 << 30), Some(512 << 20), 1 << 20, 5).unwrap();
        assert_eq!((s.pool, s.host), (1 << 30, 512 << 20));
        assert!(s.total >= s.pool + s.host + s.chunks + s.images + s.fixed);
    }

    #[test]
    fn budgets_beyond_the_machine_are_refused() {
        let Some(ram) = known_ram() else {
            return; // no /proc/meminfo: nothing to hold them against
        };
        let e = split(None, Some(2 * ram), Some(1 << 30), 1 << 20, 5)
            .unwrap_err()
            .to_string();
        assert!(e.contains("of RAM"), "{e}");
    }

    #[test]
    fn the_filters_share_comes_out_of_the_budget() {
        let plain = split(Some(512 << 20), None, None, 1 << 16, 4).unwrap();
        let s =
            split_with_shares(Some(512 << 20), None, None, 1 << 16, 4, 0, (64 << 20, 0)).unwrap();
        assert_eq!(s.filters, 64 << 20);
        assert_eq!(
            s.pool + s.host + s.chunks + s.images + s.fixed + s.filters,
            s.total
        );
        assert!(s.pool < plain.pool && s.host < plain.host);
        assert!(
            s.describe().contains("filters 64.0 MiB"),
            "{}",
            s.describe()
        );
        let e = split_with_shares(
            Some(256 << 20),
            Some(100 << 20),
            Some(60 << 20),
            0,
            4,
            0,
            (64 << 20, 0),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("does not hold") && e.contains("filters"), "{e}");
    }

    #[test]
    fn sizes_past_any_machine_are_refused_not_wrapped() {
        // A pool of 2^64 − 1 bytes summed with the rest wrapped around to
        // a small total and passed.
        let e = split(Some(1 << 30), Some(u64::MAX), None, 1 << 16, 4)
            .unwrap_err()
            .to_string();
        assert!(e.contains("does not hold"), "{e}");
        if known_ram().is_some() {
            let e = split(None, Some(u64::MAX), Some(u64::MAX), 1 << 16, 4)
                .unwrap_err()
                .to_string();
            assert!(e.contains("of RAM"), "{e}");
        }
        // Sizes past 64 bits are refused (they were taken as 2^64 − 1,
        // which `convert` and `process` then took as no bound at all).
        for big in ["99999999999999999999", "99999999999999999999TiB", "16EiB"] {
            if let Err(e) = parse_bytes(big) {
                assert!(
                    e.to_string().contains("16 EiB") || e.to_string().contains("unit"),
                    "{e}"
                );
            } else {
                panic!("{big} taken");
            }
        }
        // Bytes are whole; with a unit a fraction is bytes.
        let e = parse_bytes("1.9").unwrap_err().to_string();
        assert!(e.contains("whole number of bytes"), "{e}");
        assert_eq!(parse_bytes("1.5KiB").unwrap(), 1536);
        assert_eq!(parse_bytes("4096").unwrap(), 4096);
    }

    #[test]
    fn an_explicit_pool_takes_from_the_rest() {
        let s = split(Some(512 << 20), Some(100 << 20), None, 0, 4).unwrap();
        assert_eq!(s.pool, 100 << 20);
        assert!(s.pool + s.host + s.chunks + s.fixed <= s.total);
    }
}
