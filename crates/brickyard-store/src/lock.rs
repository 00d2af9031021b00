//! Locks between processes that write the same output: a file beside it
//! holding the writer's process id.
//!
//! The file appears with its content in one step (written under a
//! temporary name, then hard-linked into place, which fails when the lock
//! exists), so a reader never sees an empty lock. A lock whose process is
//! gone (a killed writer) is taken over; the file is removed when the
//! [`PidLock`] is dropped.

use crate::error::{IoContext, Result, StoreError};
use std::io::ErrorKind;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A lock held by this process; released when dropped.
#[derive(Debug)]
pub struct PidLock(PathBuf);

/// Who holds an existing lock.
enum Holder {
    /// A live process (its id).
    Alive(u32),
    /// A process that is gone, or a file that names none.
    Gone,
}

impl PidLock {
    /// Take the lock at `path`, or fail naming the process that holds it.
    /// `what`: what the lock keeps to one writer, for the message
    /// ("another process (pid N) is {what}").
    pub fn take(path: &Path, what: &str) -> Result<PidLock> {
        Self::acquire(path, what, None)
    }

    /// Take the lock at `path`, waiting up to `patience` while a live
    /// process holds it (for short critical sections, such as updating a
    /// shared list).
    pub fn wait(path: &Path, what: &str, patience: Duration) -> Result<PidLock> {
        Self::acquire(path, what, Some(Instant::now() + patience))
    }

    /// The lock file's path.
    pub fn path(&self) -> &Path {
        &self.0
    }

    fn acquire(path: &Path, what: &str, until: Option<Instant>) -> Result<PidLock> {
        // Temporaries of attempts killed between writing and linking:
        // cleared once, before the attempts of this call.
        remove_stale_temporaries(path);
        // Locks of processes that are gone, removed so far.
        let mut removed = 0;
        loop {
            if create_with_pid(path)? {
                return Ok(PidLock(path.to_path_buf()));
            }
            match holder(path) {
                // Released between the attempt and the look: try again.
                None => {}
                Some(Holder::Alive(pid)) => match until {
                    Some(t) if Instant::now() < t => {
                        std::thread::sleep(Duration::from_millis(20));
                    }
                    _ => {
                        // (This very process: another call of it, e.g. a
                        // second thread of a Python program.)
                        // (A lock that outlived its job in a way this
                        // cannot see: its process id taken again after a
                        // restart, or a lock without one.)
                        let stale = format!(
                            "; if no such job is running (a lock that outlived a restart), \
                             remove {}",
                            path.display()
                        );
                        let msg = match pid {
                            0 => format!(
                                "another process is {what} (the lock names none this one can \
                                 see); wait for it to end or stop it{stale}"
                            ),
                            p if p == std::process::id() => format!(
                                "another call in this process (pid {p}) is {what}; wait for it \
                                 to end"
                            ),
                            p => format!(
                                "another process (pid {p}) is {what}; wait for it to end or stop \
                                 it{stale}"
                            ),
                        };
                        return Err(StoreError::Refused {
                            path: path.into(),
                            msg,
                        });
                    }
                },
                Some(Holder::Gone) => {
                    if removed == 100 {
                        return Err(StoreError::Refused {
                            path: path.into(),
                            msg: format!(
                                "cannot take the lock for {what}: it names no running process, \
                                 yet it keeps coming back when removed"
                            ),
                        });
                    }
                    eprintln!(
                        "note: removing {} (left by an interrupted run: the lock of a process that is gone)",
                        path.display()
                    );
                    match std::fs::remove_file(path) {
                        Err(e) if e.kind() != ErrorKind::NotFound => return Err(e).at(path),
                        _ => {}
                    }
                    removed += 1;
                }
            }
        }
    }
}

impl Drop for PidLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The locks of live processes inside store `store` (its own folder and
/// the `labels/` and `derived/` folders a `process` job writes in), each
/// with the process's id (0: not known): jobs at work there.
pub fn live_locks_within(store: &Path) -> Vec<(PathBuf, u32)> {
    let mut held = vec![];
    for dir in [
        store.to_path_buf(),
        store.join("labels"),
        store.join("derived"),
    ] {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            if !(name.starts_with('.') && name.ends_with(".lock")) {
                continue;
            }
            if let Some(pid) = live_holder(&e.path()) {
                held.push((e.path(), pid));
            }
        }
    }
    held
}

/// The live process that holds the lock file `path`, if one does (0:
/// one this process cannot see into).
pub fn live_holder(path: &Path) -> Option<u32> {
    match holder(path) {
        Some(Holder::Alive(pid)) => Some(pid),
        _ => None,
    }
}

/// Whether the lock file `path` (or a temporary of a lock attempt,
/// `.NAME.PID.N.tmp`) was left by a process that is gone.
pub fn is_stale(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if name.ends_with(".tmp") {
        return attempt_pid(&name).is_some_and(|p| !alive(p));
    }
    matches!(holder(path), Some(Holder::Gone))
}

/// The process id in the name of a lock attempt's temporary,
/// `.{lock name}.{pid}.{serial}.tmp` ([`create_with_pid`]).
fn attempt_pid(file_name: &str) -> Option<u32> {
    file_name
        .strip_suffix(".tmp")?
        .rsplit('.')
        .nth(1)?
        .parse()
        .ok()
}

/// Refuse to replace or remove `store` while a live process holds a lock
/// inside it (a `process` job writing a result there).
pub fn refuse_if_in_use(store: &Path) -> Result<()> {
    match live_locks_within(store).first() {
        None => Ok(()),
        Some((lock, pid)) => Err(StoreError::Refused {
            path: store.into(),
            msg: format!(
                "a job is writing inside it ({}{}): replacing the store now would pull it from under that job; wait for it to end or stop it",
                lock.display(),
                match pid {
                    0 => String::new(),
                    p => format!(", pid {p}"),
                }
            ),
        }),
    }
}

/// Create `path` holding this process's id; `Ok(false)` when it exists.
fn create_with_pid(path: &Path) -> Result<bool> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static SERIAL: AtomicU64 = AtomicU64::new(0);
    let pid = std::process::id();
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(
        ".{name}.{pid}.{}.tmp",
        SERIAL.fetch_add(1, Ordering::Relaxed)
    ));
    if let Err(e) = std::fs::write(&tmp, format!("{pid}\n")) {
        // (Created but not written: a full disk.)
        let _ = std::fs::remove_file(&tmp);
        // Said of the folder: the temporary's name means nothing to a user.
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
        let dir = dir.unwrap_or(Path::new("."));
        return Err(StoreError::io(
            dir,
            std::io::Error::new(
                e.kind(),
                format!("cannot write in this folder (to take the lock {name}): {e}"),
            ),
        ));
    }
    let linked = std::fs::hard_link(&tmp, path);
    let _ = std::fs::remove_file(&tmp);
    match linked {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == ErrorKind::AlreadyExists => Ok(false),
        // A file system without hard links: create it in place (a reader
        // may then see it empty for a moment, which counts as held).
        Err(_) => match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(path)
        {
            Ok(mut f) => {
                use std::io::Write;
                writeln!(f, "{pid}").at(path)?;
                Ok(true)
            }
            Err(e) if e.kind() == ErrorKind::AlreadyExists => Ok(false),
            Err(e) => Err(e).at(path),
        },
    }
}

/// Remove the temporary files of lock attempts by processes that are gone
/// (killed between writing one and linking it into place).
fn remove_stale_temporaries(path: &Path) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let prefix = format!(".{name}.");
    for e in entries.flatten() {
        let f = e.file_name();
        let f = f.to_string_lossy();
        if f.starts_with(&prefix) && attempt_pid(&f).is_some_and(|p| !alive(p)) {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// Who holds the lock at `path`; `None` when it is gone.
fn holder(path: &Path) -> Option<Holder> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == ErrorKind::NotFound => return None,
        // Unreadable: held by someone this process cannot see into.
        Err(_) => return Some(Holder::Alive(0)),
    };
    let Ok(pid) = text.trim().parse::<u32>() else {
        // Empty: being written in place (no hard links), unless old.
        let young = std::fs::metadata(path)
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age < Duration::from_secs(5));
        return Some(if young && text.is_empty() {
            Holder::Alive(0)
        } else {
            Holder::Gone
        });
    };
    let written = std::fs::metadata(path).and_then(|m| m.modified()).ok();
    Some(if alive_since(pid, written) {
        Holder::Alive(pid)
    } else {
        Holder::Gone
    })
}

/// Whether process `pid` runs (without a process table to look at, every
/// process counts as running: a lock is never taken from a live writer).
fn alive(pid: u32) -> bool {
    alive_since(pid, None)
}

/// Whether process `pid` runs and, given when its lock was written, is the
/// process that wrote it. Gone: no entry in the process table; a zombie
/// (killed or ended, not yet reaped by its parent: a killed writer's lock
/// used to hold until then); or a process that started well after the lock
/// was written (another one given the writer's recycled id). Where the
/// table cannot be read, every process counts as running.
fn alive_since(pid: u32, written: Option<std::time::SystemTime>) -> bool {
    if pid == std::process::id() {
        return true;
    }
    if !Path::new("/proc/self").exists() {
        return true;
    }
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return Path::new(&format!("/proc/{pid}")).exists();
    };
    // "PID (COMM) STATE …": the name may hold spaces and parentheses, so
    // the fields are counted from the last ')'.
    let Some((_, rest)) = stat.rsplit_once(')') else {
        return true;
    };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    if matches!(fields.first(), Some(&("Z" | "X" | "x"))) {
        return false;
    }
    // Field 22, the start in clock ticks after boot (USER_HZ: 100 on
    // Linux's every architecture), is the 20th after the state.
    let start = fields.get(19).and_then(|v| v.parse::<u64>().ok());
    match (written, start, boot_time()) {
        (Some(w), Some(ticks), Some(boot)) => {
            let started = boot + Duration::from_millis(ticks * 10);
            // (Seconds of slack: the boot time is whole seconds, and
            // clocks are adjusted.)
            started <= w + Duration::from_secs(5)
        }
        _ => true,
    }
}

/// When the machine booted (`btime` of `/proc/stat`).
fn boot_time() -> Option<std::time::SystemTime> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let secs = stat
        .lines()
        .find_map(|l| l.strip_prefix("btime "))?
        .trim()
        .parse::<u64>()
        .ok()?;
    Some(std::time::UNIX_EPOCH + Duration::from_secs(secs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("brickyard-lock-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A lock this very process holds (another thread's call) is said to
    /// be another call's, not another process's to stop.
    #[test]
    fn a_lock_of_this_process_is_another_calls() {
        let d = dir("same");
        let p = d.join("s.lock");
        let held = PidLock::take(&p, "writing s").unwrap();
        let e = PidLock::take(&p, "writing s").unwrap_err().to_string();
        assert!(
            e.contains("another call in this process")
                && e.contains(&format!("pid {}", std::process::id()))
                && !e.contains("stop it"),
            "{e}"
        );
        drop(held);
        drop(PidLock::take(&p, "writing s").unwrap());
        std::fs::remove_dir_all(&d).unwrap();
    }

    /// A killed writer not yet reaped by its parent (a zombie) holds no
    /// lock; nor does a process given a writer's id after the lock was
    /// written.
    #[test]
    fn zombies_and_processes_newer_than_the_lock_hold_nothing() {
        let d = dir("zombie");
        let p = d.join("z.lock");
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let pid = child.id();
        std::fs::write(&p, pid.to_string()).unwrap();
        // Running, and started before its lock was written: it holds it.
        assert!(matches!(holder(&p), Some(Holder::Alive(x)) if x == pid));
        let e = PidLock::take(&p, "writing z").unwrap_err().to_string();
        assert!(e.contains(&format!("pid {pid}")), "{e}");
        // The same process, but the lock written an hour before it
        // started: another writer's, whose id it was given.
        let f = std::fs::File::options().write(true).open(&p).unwrap();
        f.set_modified(std::time::SystemTime::now() - Duration::from_secs(3600))
            .unwrap();
        drop(f);
        assert!(matches!(holder(&p), Some(Holder::Gone)));
        // Killed and not reaped: a zombie, gone.
        std::fs::write(&p, pid.to_string()).unwrap();
        child.kill().unwrap();
        let until = Instant::now() + Duration::from_secs(10);
        while std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|s| {
            !s.rsplit_once(')')
                .is_some_and(|(_, r)| r.trim_start().starts_with('Z'))
        }) && Instant::now() < until
        {
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(
            std::path::Path::new(&format!("/proc/{pid}")).exists(),
            "the killed child should stay in the table until reaped"
        );
        assert!(matches!(holder(&p), Some(Holder::Gone)));
        let lock = PidLock::take(&p, "writing z").unwrap();
        drop(lock);
        child.wait().unwrap();
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn one_holder_at_a_time_and_released_on_drop() {
        let d = dir("one");
        let p = d.join("x.lock");
        let a = PidLock::take(&p, "writing x").unwrap();
        assert_eq!(
            std::fs::read_to_string(&p).unwrap().trim(),
            std::process::id().to_string()
        );
        let e = PidLock::take(&p, "writing x").unwrap_err().to_string();
        assert!(
            e.contains("x.lock") && e.contains(&format!("pid {}", std::process::id())),
            "{e}"
        );
        assert!(e.contains("is writing x"), "{e}");
        drop(a);
        assert!(!p.exists());
        let _b = PidLock::take(&p, "writing x").unwrap();
        // No temporary files stay beside it.
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
        drop(_b);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_gone_process_lock_is_taken_over() {
        let d = dir("gone");
        let p = d.join("x.lock");
        // A pid above the kernel's largest (4194304) names no process.
        std::fs::write(&p, "4294967\n").unwrap();
        let l = PidLock::take(&p, "writing x").unwrap();
        assert_eq!(
            std::fs::read_to_string(l.path()).unwrap().trim(),
            std::process::id().to_string()
        );
        drop(l);
        // A temporary of a killed attempt goes with the next one.
        let stale = d.join(".x.lock.4294967.0.tmp");
        std::fs::write(&stale, "4294967\n").unwrap();
        drop(PidLock::take(&p, "writing x").unwrap());
        assert!(!stale.exists());
        // Garbage that names no process is taken over too.
        std::fs::write(&p, "not a pid\n").unwrap();
        drop(PidLock::take(&p, "writing x").unwrap());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn waiting_takes_it_when_released() {
        let d = dir("wait");
        let p = d.join("list.lock");
        let held = PidLock::take(&p, "updating the list").unwrap();
        let p2 = p.clone();
        let t = std::thread::spawn(move || {
            PidLock::wait(&p2, "updating the list", Duration::from_secs(30)).map(|_| ())
        });
        std::thread::sleep(Duration::from_millis(100));
        assert!(!t.is_finished(), "waited while the lock was held");
        drop(held);
        t.join().unwrap().unwrap();
        // A short patience gives up with the holder named.
        let _held = PidLock::take(&p, "updating the list").unwrap();
        let e = PidLock::wait(&p, "updating the list", Duration::from_millis(50)).unwrap_err();
        assert!(e.to_string().contains("updating the list"), "{e}");
        drop(_held);
        std::fs::remove_dir_all(&d).unwrap();
    }
}
