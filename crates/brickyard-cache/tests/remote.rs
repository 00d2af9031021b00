//! Bricks of a remote store through a server that injects faults: server
//! errors, stalls past the timeout, truncated bodies and reset
//! connections are retried and the bricks equal those read from disk;
//! faults that persist become failed bricks with errors that name the URL
//! and what happened, within a bounded time; access errors are not
//! retried.

use brickyard_cache::brick::BrickKey;
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_core::DType;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::storage::http::{self, HttpConfig};
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    None,
    Status(u16),
    /// Answer nothing for this long.
    Stall(Duration),
    /// Announce the whole length, send half, close.
    Truncate,
    /// Close the connection without reading the request (a reset).
    Reset,
}

type Plan = Arc<dyn Fn(u64, &str) -> Fault + Send + Sync>;

/// A file server with ranges that injects the faults its plan says, per
/// request number and path.
struct Injector {
    port: u16,
    plan: Arc<Mutex<Plan>>,
    served: Arc<AtomicU64>,
}

impl Injector {
    fn start(root: PathBuf) -> Injector {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let plan: Arc<Mutex<Plan>> = Arc::new(Mutex::new(Arc::new(|_, _| Fault::None)));
        let served = Arc::new(AtomicU64::new(0));
        let (p2, s2) = (plan.clone(), served.clone());
        std::thread::spawn(move || {
            for c in l.incoming().flatten() {
                let (root, plan, served) = (root.clone(), p2.clone(), s2.clone());
                std::thread::spawn(move || {
                    let _ = handle(c, &root, &plan, &served);
                });
            }
        });
        Injector { port, plan, served }
    }

    fn set(&self, f: impl Fn(u64, &str) -> Fault + Send + Sync + 'static) {
        *self.plan.lock().unwrap() = Arc::new(f);
    }
}

fn handle(
    mut c: TcpStream,
    root: &Path,
    plan: &Mutex<Plan>,
    served: &AtomicU64,
) -> std::io::Result<()> {
    let n = served.fetch_add(1, Ordering::SeqCst);
    // Peek at the request line for the plan without consuming it.
    std::thread::sleep(Duration::from_millis(2));
    let mut peek = [0u8; 512];
    let k = c.peek(&mut peek)?;
    let line = String::from_utf8_lossy(&peek[..k])
        .lines()
        .next()
        .unwrap_or("")
        .to_string();
    let path = line.split(' ').nth(1).unwrap_or("/").to_string();
    let fault = (plan.lock().unwrap())(n, &path);
    if fault == Fault::Reset {
        // Unread data pending: closing sends a reset.
        drop(c);
        return Ok(());
    }
    let mut r = BufReader::new(c.try_clone()?);
    let mut head = vec![];
    loop {
        let mut l = String::new();
        if r.read_line(&mut l)? == 0 || l == "\r\n" {
            break;
        }
        head.push(l);
    }
    let method = line.split(' ').next().unwrap_or("GET").to_string();
    let range = head.iter().find_map(|h| {
        h.to_ascii_lowercase()
            .strip_prefix("range: bytes=")
            .map(|v| v.trim().to_string())
    });
    match fault {
        Fault::Status(s) => {
            return c.write_all(
                format!("HTTP/1.1 {s} Injected\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                    .as_bytes(),
            );
        }
        Fault::Stall(d) => {
            std::thread::sleep(d);
            return Ok(());
        }
        _ => {}
    }
    let file = root.join(path.trim_start_matches('/'));
    let Ok(data) = std::fs::read(&file) else {
        return c.write_all(
            b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
        );
    };
    let len = data.len() as u64;
    let (status, a, b) = match range {
        None => ("200 OK", 0, len),
        Some(r) => {
            let (x, y) = r.split_once('-').unwrap();
            if x.is_empty() {
                let k: u64 = y.parse().unwrap();
                ("206 Partial Content", len - k.min(len), len)
            } else {
                let s: u64 = x.parse().unwrap();
                let e = if y.is_empty() {
                    len
                } else {
                    (y.parse::<u64>().unwrap() + 1).min(len)
                };
                ("206 Partial Content", s, e)
            }
        }
    };
    let mut out = format!(
        "HTTP/1.1 {status}\r\nContent-Length: {}\r\nConnection: close\r\n",
        b - a
    );
    if status.starts_with("206") {
        out.push_str(&format!("Content-Range: bytes {a}-{}/{len}\r\n", b - 1));
    }
    out.push_str("\r\n");
    c.write_all(out.as_bytes())?;
    if method == "HEAD" {
        return Ok(());
    }
    let body = &data[a as usize..b as usize];
    if fault == Fault::Truncate {
        c.write_all(&body[..body.len() / 2])?;
        c.flush()?;
        return Ok(());
    }
    c.write_all(body)
}

fn store(dir: &Path) -> PathBuf {
    let out = dir.join("v.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, [64, 64, 64], DType::U16);
    let opts = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &out, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    out
}

fn loader(p: &Path) -> Loader {
    Loader::open(p, [16; 3], 1, 4, Arc::new(HostCache::new(64 << 20))).unwrap()
}

fn all_keys(l: &Loader) -> Vec<BrickKey> {
    let g = l.geometry();
    (0..g.levels.len())
        .flat_map(|lv| g.keys(lv, 0).collect::<Vec<_>>())
        .collect()
}

/// A shard file (not metadata, not statistics).
fn is_shard(p: &str) -> bool {
    p.contains("/c/") && !p.contains("_brickyard")
}

#[test]
fn remote_faults_are_retried_then_become_failed_bricks() {
    http::configure(HttpConfig {
        timeout: Duration::from_millis(400),
        connect_timeout: Duration::from_millis(400),
        retries: 3,
        backoff: Duration::from_millis(5),
        max_in_flight: 8,
        ..HttpConfig::default()
    });
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let inj = Injector::start(dir.path().to_path_buf());
    let url = PathBuf::from(format!("http://127.0.0.1:{}/v.ome.zarr", inj.port));
    let local = loader(&st);
    let keys = all_keys(&local);
    assert!(keys.len() > 8);

    // Every other shard read fails, each kind of fault in turn: all are
    // retried and every brick equals the local one.
    let kinds = [
        Fault::Status(500),
        Fault::Stall(Duration::from_millis(1500)),
        Fault::Truncate,
        Fault::Reset,
        Fault::Status(503),
    ];
    inj.set(move |n, p| {
        if is_shard(p) && n % 2 == 0 {
            kinds[(n as usize / 2) % kinds.len()]
        } else {
            Fault::None
        }
    });
    let before = http::stats();
    let remote = loader(&url);
    let mut data = 0;
    for k in &keys {
        let a = local.load_now(k).unwrap();
        let b = remote.load_now(k).unwrap_or_else(|e| panic!("{k:?}: {e}"));
        assert_eq!(a, b, "{k:?}");
        data += (a.bytes_read > 0) as usize;
    }
    assert!(data > 4, "too few bricks read data ({data})");
    let st1 = http::stats();
    assert!(st1.retries - before.retries >= 5, "{st1:?}");
    // A loader keeps the shard indexes it read; a second loader on the same
    // URL finds them in the HTTP client's index cache instead of asking the
    // server again.
    let again = loader(&url);
    for k in keys.iter().filter(|k| k.level == 0).take(4) {
        again.load_now(k).unwrap_or_else(|e| panic!("{k:?}: {e}"));
    }
    let st1 = http::stats();
    assert!(st1.index_hits > 0, "shard indexes are read again: {st1:?}");

    // Persistent faults: failed bricks, each error naming the URL and the
    // fault, in bounded time; no worker hangs or dies.
    for (fault, says) in [
        (Fault::Status(500), "HTTP 500"),
        (Fault::Stall(Duration::from_secs(3)), "timed out"),
        (Fault::Truncate, "truncated"),
        (Fault::Reset, "connection"),
        (Fault::Status(403), "HTTP 403"),
    ] {
        inj.set(move |_, p| if is_shard(p) { fault } else { Fault::None });
        let remote = loader(&url);
        let level0: Vec<BrickKey> = keys
            .iter()
            .filter(|k| k.level == 0 && local.load_now(k).unwrap().bytes_read > 0)
            .take(6)
            .copied()
            .collect();
        let t0 = Instant::now();
        remote.request(&level0.iter().map(|k| (*k, 1)).collect::<Vec<_>>());
        assert!(
            remote.wait_idle(Duration::from_secs(60)),
            "{fault:?}: the loader hangs"
        );
        let fails = remote.take_failures();
        let loaded = remote.poll();
        assert!(
            loaded.is_empty(),
            "{fault:?}: {} bricks loaded",
            loaded.len()
        );
        assert_eq!(fails.len(), level0.len(), "{fault:?}");
        for f in &fails {
            assert!(
                f.message.contains(url.to_str().unwrap()),
                "{fault:?}: {}",
                f.message
            );
            assert!(f.message.contains(says), "{fault:?}: {}", f.message);
        }
        if let Fault::Status(403) = fault {
            assert!(
                !fails[0].message.contains("attempts"),
                "403 was retried: {}",
                fails[0].message
            );
        } else {
            assert!(
                fails[0].message.contains("after 4 attempts"),
                "{}",
                fails[0].message
            );
        }
        assert!(
            t0.elapsed() < Duration::from_secs(45),
            "{fault:?}: {:?}",
            t0.elapsed()
        );
        // The view goes on: once the server is healthy again the same
        // loader reads the bricks.
        inj.set(|_, _| Fault::None);
        remote.retry_failed();
        let k = fails[0].key;
        assert_eq!(remote.load_now(&k).unwrap(), local.load_now(&k).unwrap());
    }
    assert!(inj.served.load(Ordering::SeqCst) > 0);
}
