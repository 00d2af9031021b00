//! Read-ahead for reads around the page cache: hinted byte ranges of local
//! files are read (`O_DIRECT`) by a few background threads into buffers
//! of a bounded staging area, which the reads that follow take them from.
//!
//! Through the page cache a hint is `posix_fadvise(WILLNEED)`, and the
//! kernel's pages are the staging area; around it the process keeps its
//! own. The area holds at most [`STAGE_BYTES`] of buffers (the oldest
//! staged ranges are given up when a reader needs room), and as many bytes
//! of ranges queued (a hint past that is dropped). Nothing depends on it
//! but speed: a read whose
//! range is not staged reads the file itself, and a staged read that failed
//! is read again by the reader, which then reports the error.

use std::collections::VecDeque;
use std::fs::File;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};

/// The most bytes of buffers held, and of ranges queued.
pub(super) const STAGE_BYTES: usize = super::DIRECT_STAGE_BYTES as usize;

/// Background reader threads: enough reads in flight to keep a disk busy
/// while the loader's threads decode.
const READERS: usize = 4;

/// One hinted range of a file.
struct Entry {
    id: u64,
    file: Arc<PathBuf>,
    range: Range<u64>,
    state: State,
    /// Bytes of the range taken so far (a byte taken twice counts twice).
    taken: u64,
}

enum State {
    Queued,
    Reading,
    /// The bytes of `range` read (fewer at the end of the file), in an
    /// aligned buffer: `(buffer, offset of the range in it, bytes read)`.
    Ready(Arc<(Vec<u8>, usize, usize)>),
}

#[derive(Default)]
struct Area {
    /// In hint order (oldest first): what is given up first for room.
    entries: VecDeque<Entry>,
    /// Bytes of the queued entries' ranges (at most the budget).
    queued: usize,
    /// Bytes of the buffers of entries being read or read, and of the pool
    /// (at most the budget, but for buffers a taker still holds).
    held: usize,
    /// Buffers of entries taken or given up, for reuse.
    pool: Vec<Vec<u8>>,
    next_id: u64,
    started: bool,
    /// The most bytes queued, and of buffers held ([`STAGE_BYTES`]).
    budget: usize,
}

pub(super) struct Stage {
    area: Mutex<Area>,
    /// Signalled when an entry is queued (readers wait) or read (a taker of
    /// its range waits), and when a buffer comes back (a reader waits).
    changed: Condvar,
}

/// The process's staging area, of [`STAGE_BYTES`].
pub(super) fn global() -> &'static Arc<Stage> {
    static S: OnceLock<Arc<Stage>> = OnceLock::new();
    S.get_or_init(|| Stage::new(STAGE_BYTES))
}

fn lock(s: &Stage) -> MutexGuard<'_, Area> {
    s.area.lock().unwrap_or_else(|e| e.into_inner())
}

fn covers(e: &Entry, p: &Path, r: &Range<u64>) -> bool {
    *e.file == p && e.range.start <= r.start && r.end <= e.range.end
}

impl Area {
    /// Take entry `i` out, its buffer into the pool.
    fn remove(&mut self, i: usize) {
        let e = self.entries.remove(i).expect("an entry's index");
        match e.state {
            State::Queued => self.queued -= (e.range.end - e.range.start) as usize,
            State::Reading => {}
            State::Ready(b) => {
                self.held -= b.0.len();
                if let Ok((buf, _, _)) = Arc::try_unwrap(b) {
                    self.pool_put(buf);
                }
            }
        }
    }

    /// Keep `buf` (no longer counted in `held`) for reuse, where there is room.
    fn pool_put(&mut self, buf: Vec<u8>) {
        if self.held + buf.len() <= self.budget {
            self.held += buf.len();
            self.pool.push(buf);
        }
    }
}

/// A buffer of at least `len` bytes for a reader, counted in `held`: the
/// pool's smallest that fits, else a new one where there is room, else
/// room made by giving up the oldest read entry or a pooled buffer, else
/// (every byte in reads in flight) after waiting for one to end.
fn obtain<'a>(
    s: &'a Stage,
    mut a: MutexGuard<'a, Area>,
    len: usize,
) -> (MutexGuard<'a, Area>, Vec<u8>) {
    loop {
        let best = (0..a.pool.len())
            .filter(|&i| a.pool[i].len() >= len)
            .min_by_key(|&i| a.pool[i].len());
        if let Some(i) = best {
            let b = a.pool.swap_remove(i);
            return (a, b);
        }
        if a.held + len <= a.budget {
            a.held += len;
            return (a, vec![0u8; len]);
        }
        if let Some(i) = a
            .entries
            .iter()
            .position(|e| matches!(e.state, State::Ready(_)))
        {
            a.remove(i);
        } else if let Some(b) = a.pool.pop() {
            a.held -= b.len();
        } else {
            a = s.changed.wait(a).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// Queue `ranges` (aligned to `align`) of `p` to be read around the page
/// cache. Returns how many were queued (not already hinted, and with room).
impl Stage {
    /// A staging area of `budget` bytes, its readers started with its first hint.
    pub(super) fn new(budget: usize) -> Arc<Stage> {
        Arc::new(Stage {
            area: Mutex::new(Area {
                budget,
                ..Area::default()
            }),
            changed: Condvar::new(),
        })
    }

    pub(super) fn hint(self: &Arc<Self>, p: &Path, ranges: &[Range<u64>], align: u64) -> usize {
        let s = &**self;
        let mut a = lock(s);
        let file = Arc::new(p.to_path_buf());
        let mut queued = 0;
        for r in ranges {
            let r = r.start / align * align..r.end.div_ceil(align) * align;
            let len = (r.end - r.start) as usize;
            if r.is_empty()
                || a.queued + len > a.budget
                || len + align as usize > a.budget / 4
                || a.entries.iter().any(|e| covers(e, p, &r))
            {
                continue;
            }
            let id = a.next_id;
            a.next_id += 1;
            a.queued += len;
            a.entries.push_back(Entry {
                id,
                file: file.clone(),
                range: r,
                state: State::Queued,
                taken: 0,
            });
            queued += 1;
        }
        if queued > 0 && !a.started {
            a.started = true;
            for i in 0..READERS {
                let me = self.clone();
                let spawned = std::thread::Builder::new()
                    .name(format!("brickyard-read-{i}"))
                    .spawn(move || reader(&me));
                if spawned.is_err() && i == 0 {
                    // No reader: nothing is read ahead; every read reads itself.
                    a.started = false;
                    while !a.entries.is_empty() {
                        a.remove(0);
                    }
                    return 0;
                }
            }
        }
        drop(a);
        s.changed.notify_all();
        queued
    }

    /// The staged bytes `range` (aligned) of `p`, when a hint covered them:
    /// `f` gets them (the range's bytes read, fewer at the file's end) and its
    /// result is returned. Waits for a read in flight; a range still queued is
    /// taken off the queue and left to the caller. `None`: not staged.
    /// The staged bytes `range` (aligned) of `p`, when hints covered them (in
    /// one range or in neighbouring ones): `f` gets them (the range's bytes
    /// read, fewer at the file's end) and its result is returned. Waits for
    /// reads in flight; ranges still queued are taken off the queue and left
    /// to the caller. `None`: not staged.
    pub(super) fn take<R>(
        &self,
        p: &Path,
        range: Range<u64>,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Option<R> {
        let s = self;
        let mut a = lock(s);
        let parts = loop {
            // The staged ranges that cover `range`, in order, each starting
            // where the one before ends or earlier.
            let mut over: Vec<usize> = (0..a.entries.len())
                .filter(|&i| {
                    let e = &a.entries[i];
                    *e.file == p && e.range.start < range.end && range.start < e.range.end
                })
                .collect();
            over.sort_by_key(|&i| {
                (
                    a.entries[i].range.start,
                    std::cmp::Reverse(a.entries[i].range.end),
                )
            });
            let mut chosen = vec![];
            let mut at = range.start;
            for i in over {
                let r = &a.entries[i].range;
                if at >= range.end || r.start > at {
                    break;
                }
                if r.end > at {
                    chosen.push(i);
                    at = r.end;
                }
            }
            if at < range.end {
                return None;
            }
            if chosen
                .iter()
                .any(|&i| matches!(a.entries[i].state, State::Queued))
            {
                // Read by the caller instead; the other parts stay for others.
                chosen.sort_unstable();
                for &i in chosen.iter().rev() {
                    if matches!(a.entries[i].state, State::Queued) {
                        a.remove(i);
                    }
                }
                return None;
            }
            if chosen
                .iter()
                .any(|&i| matches!(a.entries[i].state, State::Reading))
            {
                a = s.changed.wait(a).unwrap_or_else(|e| e.into_inner());
                continue;
            }
            break chosen;
        };
        // The parts' bytes, and what each gives of `range`; a part whose bytes
        // are all taken is not asked for again, and goes (its buffer back once
        // read).
        let mut pieces = Vec::with_capacity(parts.len());
        let mut done = vec![];
        // Neighbouring staged ranges may overlap: each gives from where the
        // one before ended.
        let mut from = range.start;
        for &i in &parts {
            let e = &mut a.entries[i];
            let State::Ready(b) = &e.state else {
                unreachable!("chosen when read")
            };
            let lo = from.max(e.range.start);
            let hi = range.end.min(e.range.end);
            from = hi;
            pieces.push((b.clone(), (lo - e.range.start) as usize, (hi - lo) as usize));
            e.taken += hi - lo;
            if e.taken >= e.range.end - e.range.start {
                done.push(e.id);
            }
        }
        let mut gone = vec![];
        for id in done {
            if let Some(i) = a.entries.iter().position(|e| e.id == id) {
                let e = a.entries.remove(i).expect("found above");
                if let State::Ready(b) = e.state {
                    a.held -= b.0.len();
                    gone.push(b);
                }
            }
        }
        drop(a);
        let r = if let [(b, at, n)] = &pieces[..] {
            let (data, off, got) = &**b;
            let end = (at + n).min(*got);
            f(&data[off + (*at).min(end)..off + end])
        } else {
            // In neighbouring ranges: put together (a short piece, at the
            // file's end, is the last).
            let mut whole = Vec::with_capacity((range.end - range.start) as usize);
            for (b, at, n) in &pieces {
                let (data, off, got) = &**b;
                let end = (at + n).min(*got);
                whole.extend_from_slice(&data[off + (*at).min(end)..off + end]);
                if end < at + n {
                    break;
                }
            }
            f(&whole)
        };
        drop(pieces);
        let back: Vec<Vec<u8>> = gone
            .into_iter()
            .filter_map(|b| Arc::try_unwrap(b).ok().map(|(v, _, _)| v))
            .collect();
        if !back.is_empty() {
            let mut a = lock(s);
            for b in back {
                a.pool_put(b);
            }
            drop(a);
            s.changed.notify_all();
        }
        Some(r)
    }
}

/// A background reader: reads queued ranges, oldest first.
fn reader(s: &Stage) {
    loop {
        let mut a = lock(s);
        let (id, file, range) = loop {
            if let Some(e) = a
                .entries
                .iter_mut()
                .find(|e| matches!(e.state, State::Queued))
            {
                e.state = State::Reading;
                let r = (e.id, e.file.clone(), e.range.clone());
                a.queued -= (r.2.end - r.2.start) as usize;
                break r;
            }
            a = s.changed.wait(a).unwrap_or_else(|e| e.into_inner());
        };
        let len = (range.end - range.start) as usize;
        let (a, mut buf) = obtain(s, a, len + super::local::DIRECT_ALIGN);
        drop(a);
        let off = buf.as_ptr().align_offset(super::local::DIRECT_ALIGN);
        let got = read_direct(&file, &mut buf[off..off + len], range.start);
        let mut a = lock(s);
        let i = a.entries.iter().position(|e| e.id == id);
        match (i, got) {
            (Some(i), Some(got)) => a.entries[i].state = State::Ready(Arc::new((buf, off, got))),
            (i, _) => {
                // Failed: the taker reads it again and reports the error.
                if let Some(i) = i {
                    a.entries.remove(i);
                }
                a.held -= buf.len();
                a.pool_put(buf);
            }
        }
        drop(a);
        s.changed.notify_all();
    }
}

fn read_direct(p: &Path, buf: &mut [u8], at: u64) -> Option<usize> {
    let f: File = super::local::open_direct(p).ok()???;
    super::local::read_up_to(&f, buf, at).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file of `len` bytes (`i % 251`) on the build's disk, and whether
    /// that disk takes reads around the page cache.
    fn file(name: &str, len: usize) -> (tempfile::TempDir, PathBuf, Vec<u8>, bool) {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/tmp");
        std::fs::create_dir_all(&root).unwrap();
        let dir = tempfile::tempdir_in(root).unwrap();
        let p = dir.path().join(name);
        let data: Vec<u8> = (0..len).map(|i| (i % 251) as u8).collect();
        std::fs::write(&p, &data).unwrap();
        let direct = matches!(super::super::local::open_direct(&p), Ok(Some(Some(_))));
        (dir, p, data, direct)
    }

    fn wait_read(s: &Stage) {
        for _ in 0..500 {
            let a = lock(s);
            if a.entries.iter().all(|e| matches!(e.state, State::Ready(_))) {
                return;
            }
            drop(a);
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        panic!("hinted ranges not read in 1 s");
    }

    #[test]
    fn hints_past_the_budget_are_dropped_and_buffers_stay_within_it() {
        let (_d, p, data, direct) = file("a.bin", 1 << 20);
        let budget = 256 << 10;
        let s = Stage::new(budget);
        // 16 ranges of 32 KiB: 8 fit the queue.
        let ranges: Vec<Range<u64>> = (0..16u64).map(|i| i << 15..(i + 1) << 15).collect();
        assert_eq!(s.hint(&p, &ranges, 4096), 8);
        if !direct {
            eprintln!("note: no O_DIRECT on this disk: the readers fail, nothing is staged");
        }
        wait_read(&s);
        assert!(lock(&s).held <= budget);
        // A range too large for a quarter of the budget is not hinted; one
        // already staged (the last; the first was given up for room) is not
        // hinted again.
        let big: Range<u64> = 0..64 << 10;
        assert_eq!(s.hint(&p, std::slice::from_ref(&big), 4096), 0);
        let last = (7 << 15) + 4096..(7 << 15) + 8192;
        assert_eq!(s.hint(&p, &[last], 4096), usize::from(!direct));
        // The next 8 once the first are read: buffers of the older ones
        // are taken back for room, never more than the budget held.
        assert_eq!(s.hint(&p, &ranges[8..], 4096), 8);
        wait_read(&s);
        let a = lock(&s);
        assert!(a.held <= budget, "{} bytes held", a.held);
        let staged = a.entries.len();
        drop(a);
        if direct {
            // Each buffer is its range and an alignment's slack: 7 of 36 KiB
            // fit 256 KiB, the oldest given up.
            assert_eq!(staged, 7);
            let got = s.take(&p, 15 << 15..16 << 15, |b| b.to_vec()).unwrap();
            assert_eq!(got, data[15 << 15..16 << 15]);
            assert!(s.take(&p, 0..4096, |b| b.len()).is_none(), "given up");
        } else {
            assert_eq!(staged, 0);
        }
    }

    #[test]
    fn a_range_taken_in_parts_goes_when_all_of_it_is_taken() {
        let (_d, p, data, direct) = file("b.bin", 100_000);
        let s = Stage::new(1 << 20);
        assert_eq!(s.hint(&p, &[0..(64 << 10), 64 << 10..100_000], 4096), 2);
        wait_read(&s);
        if !direct {
            eprintln!("note: no O_DIRECT on this disk: the readers fail, nothing is staged");
            assert!(s.take(&p, 0..4096, |b| b.len()).is_none());
            return;
        }
        // The second range reaches past the file's end: its bytes stop there.
        let tail = s.take(&p, 64 << 10..102_400, |b| b.to_vec()).unwrap();
        assert_eq!(tail, data[64 << 10..]);
        assert_eq!(lock(&s).entries.len(), 1, "taken whole, gone");
        let mid = s.take(&p, 8192..(64 << 10), |b| b.to_vec()).unwrap();
        assert_eq!(mid, data[8192..64 << 10]);
        assert_eq!(
            lock(&s).entries.len(),
            1,
            "the first 8 KiB are still to come"
        );
        let head = s.take(&p, 0..8192, |b| b.to_vec()).unwrap();
        assert_eq!(head, data[..8192]);
        let a = lock(&s);
        assert!(a.entries.is_empty(), "all of it taken");
        assert_eq!(
            a.held,
            a.pool.iter().map(Vec::len).sum::<usize>(),
            "buffers pooled"
        );
        drop(a);
        assert!(s.take(&p, 0..4096, |b| b.len()).is_none());
    }

    #[test]
    fn overlapping_ranges_give_each_byte_once() {
        let (_d, p, data, direct) = file("c.bin", 100_000);
        let s = Stage::new(1 << 20);
        // Hints of neighbouring chunks whose blocks overlap, and one inside
        // both that is not hinted again.
        let hints = [0..8000, 5000..12_000, 11_000..20_000, 6000..7000];
        assert_eq!(s.hint(&p, &hints, 4096), 3);
        wait_read(&s);
        if !direct {
            eprintln!("note: no O_DIRECT on this disk: the readers fail, nothing is staged");
            assert!(s.take(&p, 0..20_480, |b| b.len()).is_none());
            return;
        }
        let got = s.take(&p, 0..20_480, |b| b.to_vec()).unwrap();
        assert_eq!(got, data[..20_480]);
    }
}
