//! Reads over HTTP(S): ranged GETs with bounded requests in flight,
//! retries with backoff, timeouts, coalescing of nearby ranges and a cache
//! of shard indexes (suffix reads).
//!
//! What is retried: server errors (5xx), 429, timeouts, refused or reset
//! connections and truncated bodies; a request the server accepted and
//! did not answer, once. No connection, no answer and a gateway's 502/504
//! count toward the host being down, whose requests then fail at once for
//! a while. What is not: 401/403 (access), 404
//! (a missing value reads as absent, which Zarr means as "fill value"),
//! 416 and other client errors. Every error names the URL, the bytes
//! asked for and what happened (`HTTP 403 Forbidden`, `timed out after
//! 30 s`, `body truncated: 100 of 4096 bytes`), and after the last retry
//! says how many attempts were made. Messages show URLs without
//! credentials or query values ([`redact`]); URLs with either are refused.
//!
//! Replaced files: the ETag a shard's index (or size) was read with is
//! remembered, and the ranges read at offsets from it are asked for with
//! `If-Match`; a 412 (or an answer of another ETag) fails the read with
//! "the file changed on the server …" and drops what was cached of it.
//! Metadata documents are used for a second, then asked for again with
//! `If-None-Match`. A file whose reads failed after all their retries is
//! tried once per read (not while another read of it is under way) for
//! 30 s, so that the bricks of a failing shard fail fast.

use super::Span;
use crate::error::{Result, StoreError};
use std::collections::{HashMap, VecDeque};
use std::io::Read;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::{Duration, Instant};

/// How remote stores are read.
#[derive(Clone, Debug)]
pub struct HttpConfig {
    /// Longest time for one request, from connecting to the last byte.
    pub timeout: Duration,
    /// Longest time to connect.
    pub connect_timeout: Duration,
    /// Longest wait for the answer's headers once the request is sent (a
    /// server that accepts connections but never answers); used where
    /// shorter than `timeout`.
    pub response_timeout: Duration,
    /// Attempts after the first for a failure worth retrying.
    pub retries: u32,
    /// Wait before the first retry; doubled for each further one (with
    /// up to a quarter more at random), at most 8 s.
    pub backoff: Duration,
    /// Most requests in flight at once, over all threads.
    pub max_in_flight: usize,
    /// Ranges of one value closer than this are read in one request.
    pub coalesce_gap: u64,
    /// Bearer token sent with every request (`Authorization: Bearer …`).
    pub token: Option<String>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        HttpConfig {
            timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(10),
            response_timeout: Duration::from_secs(10),
            retries: 4,
            backoff: Duration::from_millis(200),
            max_in_flight: 16,
            coalesce_gap: 64 << 10,
            token: None,
        }
    }
}

impl HttpConfig {
    /// The defaults, changed by the environment: `BRICKYARD_TOKEN` (bearer
    /// token), `BRICKYARD_HTTP_TIMEOUT` (seconds per request),
    /// `BRICKYARD_HTTP_RETRIES`, `BRICKYARD_HTTP_IN_FLIGHT`. A value that
    /// does not parse is an error naming the variable.
    pub fn from_env() -> std::result::Result<Self, String> {
        let mut c = HttpConfig::default();
        let var = |k: &str| std::env::var(k).ok().filter(|v| !v.trim().is_empty());
        c.token = var("BRICKYARD_TOKEN").map(|t| t.trim().to_string());
        if let Some(why) = c.token.as_deref().and_then(token_problem) {
            return Err(why);
        }
        if let Some(v) = var("BRICKYARD_HTTP_TIMEOUT") {
            let s: f64 = v
                .trim()
                .parse()
                .ok()
                .filter(|s: &f64| *s > 0.0 && s.is_finite())
                .ok_or(format!(
                    "BRICKYARD_HTTP_TIMEOUT: expected seconds > 0, found {v:?}"
                ))?;
            c.timeout = Duration::from_secs_f64(s);
            c.connect_timeout = c.connect_timeout.min(c.timeout);
        }
        if let Some(v) = var("BRICKYARD_HTTP_RETRIES") {
            c.retries = v.trim().parse().ok().filter(|&n| n <= 20).ok_or(format!(
                "BRICKYARD_HTTP_RETRIES: expected 0 to 20, found {v:?}"
            ))?;
        }
        if let Some(v) = var("BRICKYARD_HTTP_IN_FLIGHT") {
            c.max_in_flight = v
                .trim()
                .parse()
                .ok()
                .filter(|&n| (1..=1024).contains(&n))
                .ok_or(format!(
                    "BRICKYARD_HTTP_IN_FLIGHT: expected 1 to 1024, found {v:?}"
                ))?;
        }
        Ok(c)
    }
}

/// Counters of the remote reads since the program started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HttpStats {
    pub requests: u64,
    pub retries: u64,
    pub failures: u64,
    pub bytes: u64,
    pub index_hits: u64,
}

/// Largest merged range of a coalesced read.
const COALESCE_MAX: u64 = 16 << 20;
/// Bytes of shard indexes (suffix reads) kept.
const INDEX_CACHE_BYTES: usize = 32 << 20;
/// Longest wait between two attempts.
const BACKOFF_MAX: Duration = Duration::from_secs(8);

static CLIENT: RwLock<Option<Arc<Client>>> = RwLock::new(None);

/// Set how remote stores are read (once at start; later calls replace the
/// client, requests under way finish with the old one).
pub fn configure(cfg: HttpConfig) {
    *CLIENT.write().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(Client::new(cfg)));
}

/// The client, made from [`HttpConfig::from_env`] (the defaults where a
/// variable does not parse; the CLI checks them first) when none was
/// configured.
pub fn client() -> Arc<Client> {
    if let Some(c) = CLIENT.read().unwrap_or_else(|e| e.into_inner()).as_ref() {
        return c.clone();
    }
    let mut w = CLIENT.write().unwrap_or_else(|e| e.into_inner());
    w.get_or_insert_with(|| {
        Arc::new(Client::new(HttpConfig::from_env().unwrap_or_else(|_| {
            // A token that cannot be sent stays, so that each request
            // names the variable (not a 401 asking for a token).
            HttpConfig {
                token: std::env::var("BRICKYARD_TOKEN")
                    .ok()
                    .map(|t| t.trim().to_string())
                    .filter(|t| !t.is_empty()),
                ..HttpConfig::default()
            }
        })))
    })
    .clone()
}

/// Counters of the current client.
pub fn stats() -> HttpStats {
    let c = client();
    HttpStats {
        requests: c.requests.load(Ordering::Relaxed),
        retries: c.retries.load(Ordering::Relaxed),
        failures: c.failures.load(Ordering::Relaxed),
        bytes: c.bytes.load(Ordering::Relaxed),
        index_hits: c.index_hits.load(Ordering::Relaxed),
    }
}

/// A counting semaphore bounding the requests in flight.
struct Slots {
    free: Mutex<usize>,
    cv: Condvar,
}

struct Permit<'a>(&'a Slots);

impl Slots {
    fn acquire(&self) -> Permit<'_> {
        let mut n = self.free.lock().unwrap_or_else(|e| e.into_inner());
        while *n == 0 {
            n = self.cv.wait(n).unwrap_or_else(|e| e.into_inner());
        }
        *n -= 1;
        Permit(self)
    }
}

impl Drop for Permit<'_> {
    fn drop(&mut self) {
        *self.0.free.lock().unwrap_or_else(|e| e.into_inner()) += 1;
        self.0.cv.notify_one();
    }
}

/// The last bytes of a value and the value's length.
type Suffix = (Arc<Vec<u8>>, u64);

/// Suffix reads (shard indexes) with the length of their value, first in
/// first out under a byte budget.
#[derive(Default)]
struct IndexCache {
    map: HashMap<(String, u64), Suffix>,
    order: VecDeque<(String, u64)>,
    bytes: usize,
}

impl IndexCache {
    /// Forget the indexes of the files `f` names.
    fn remove_if(&mut self, f: impl Fn(&str) -> bool) {
        let mut freed = 0;
        self.map.retain(|(u, _), (b, _)| {
            let keep = !f(u);
            if !keep {
                freed += b.len();
            }
            keep
        });
        let map = &self.map;
        self.order.retain(|k| map.contains_key(k));
        self.bytes -= freed;
    }

    fn put(&mut self, k: (String, u64), v: Arc<Vec<u8>>, len: u64) {
        if v.len() > INDEX_CACHE_BYTES {
            return;
        }
        while self.bytes + v.len() > INDEX_CACHE_BYTES {
            let Some(old) = self.order.pop_front() else {
                break;
            };
            if let Some((b, _)) = self.map.remove(&old) {
                self.bytes -= b.len();
            }
        }
        self.bytes += v.len();
        if let Some((b, _)) = self.map.insert(k.clone(), (v, len)) {
            self.bytes -= b.len();
        } else {
            self.order.push_back(k);
        }
    }
}

/// One failed attempt.
struct Failure {
    retry: bool,
    /// The file is not the one its index was read from (412, or another
    /// ETag): what was cached of it is dropped.
    changed: bool,
    /// Nobody there: no connection (refused, unreachable, connect timed
    /// out) or no answer to the request sent; counts toward the host
    /// being down.
    unreachable: bool,
    /// Most attempts after the first for this kind of failure (a request
    /// a server accepted and did not answer is tried once more, not on
    /// the whole schedule: its wait is long, and a second silence says
    /// enough).
    most_retries: u32,
    /// A request sent and not answered: it waited the whole response
    /// timeout, and counts as [`SILENCE_COUNTS`] attempts toward the host
    /// being down.
    silence: bool,
    what: String,
}

impl Failure {
    fn retry(what: impl Into<String>) -> Self {
        Failure {
            retry: true,
            changed: false,
            unreachable: false,
            most_retries: u32::MAX,
            silence: false,
            what: what.into(),
        }
    }
    fn fatal(what: impl Into<String>) -> Self {
        Failure {
            retry: false,
            changed: false,
            unreachable: false,
            most_retries: u32::MAX,
            silence: false,
            what: what.into(),
        }
    }
    fn unreachable(what: impl Into<String>) -> Self {
        Failure {
            retry: true,
            changed: false,
            unreachable: true,
            most_retries: u32::MAX,
            silence: false,
            what: what.into(),
        }
    }
    fn changed() -> Self {
        Failure {
            retry: false,
            changed: true,
            unreachable: false,
            most_retries: 0,
            silence: false,
            what: "the file changed on the server since its index was read (store replaced?): \
                   open the store again"
                .to_string(),
        }
    }
}

/// Attempts that found nobody there (no connection, or no answer to a
/// request sent) in a row, over all requests to a host, after which it
/// counts as down.
const HOST_DOWN_AFTER: u32 = 6;
/// What a request sent and not answered within the response timeout
/// counts toward [`HOST_DOWN_AFTER`]: each such attempt waited the whole
/// timeout (10 s), so two in a row are enough.
const SILENCE_COUNTS: u32 = 3;
/// How long requests to a host that is down fail without trying; doubled
/// each time a try after the pause fails too, up to [`HOST_PAUSE_MAX`].
const HOST_PAUSE: Duration = Duration::from_secs(5);
const HOST_PAUSE_MAX: Duration = Duration::from_secs(60);

/// What the client knows of a host's health. A server that went away
/// would otherwise cost every value read from it its whole schedule of
/// retries (a render of a few hundred bricks took half an hour to give
/// up): once `HOST_DOWN_AFTER` attempts in a row found nobody there, its
/// requests fail at once for a pause, then one attempt tries again. Any
/// answer (of any HTTP status) makes it healthy again.
#[derive(Default)]
struct HostHealth {
    fails_in_a_row: u32,
    down_until: Option<Instant>,
    /// Since when the one attempt after a pause is under way: meanwhile
    /// the host's other requests fail without trying (each would wait
    /// out the same timeout).
    probe_since: Option<Instant>,
    pause: Duration,
    last: String,
}

/// The `scheme://host:port` part of a URL.
fn host_of(url: &str) -> &str {
    let start = url.find("://").map(|i| i + 3).unwrap_or(0);
    let end = url[start..]
        .find('/')
        .map(|i| start + i)
        .unwrap_or(url.len());
    &url[..end]
}

/// Why `token` cannot go into an `Authorization` header (a line break or
/// another control character), naming the variable it comes from.
fn token_problem(token: &str) -> Option<String> {
    let bad = token.chars().find(|c| c.is_control() && *c != '\t')?;
    Some(format!(
        "BRICKYARD_TOKEN: the token holds a control character ({bad:?}, e.g. a line break), \
         which cannot be sent in a header: give the token on one line"
    ))
}

/// The authority (`user@host:port`) of an `http(s)://` URL.
fn authority(url: &str) -> &str {
    let start = url.find("://").map(|i| i + 3).unwrap_or(0);
    let rest = &url[start..];
    let end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    &rest[..end]
}

/// `url` as it may be shown: without credentials (`user:password@`) and
/// with the values of a query string left out (`?token=…`).
pub fn redact(url: &str) -> String {
    let mut out = url.to_string();
    let auth = authority(url);
    if let Some(at) = auth.rfind('@') {
        let start = url.find("://").map(|i| i + 3).unwrap_or(0);
        out.replace_range(start..start + at + 1, "");
    }
    if let Some(q) = out.find(['?', '#']) {
        let tail: String = out[q + 1..]
            .split('&')
            .map(|kv| match kv.split_once('=') {
                Some((k, _)) => format!("{k}=…"),
                None => "…".to_string(),
            })
            .collect::<Vec<_>>()
            .join("&");
        let mark = &out[q..q + 1].to_string();
        out.truncate(q);
        out.push_str(mark);
        out.push_str(&tail);
    }
    out
}

/// Why the `http(s)://` URL `url` cannot be read, if it cannot: it holds
/// credentials (which are not sent), a query string or fragment (keys
/// are joined onto a store's path, so `…zarr?token=x` would become
/// `…zarr?token=x/zarr.json`), or a port outside 1 to 65535.
fn check_url(url: &str) -> std::result::Result<(), String> {
    let lower = url.get(..8).unwrap_or(url).to_ascii_lowercase();
    if !(lower.starts_with("http://") || lower.starts_with("https://")) {
        return Ok(());
    }
    let auth = authority(url);
    if auth.is_empty() {
        return Err("the URL names no host (expected http(s)://HOST[:PORT]/PATH)".to_string());
    }
    if auth.contains('@') {
        return Err(
            "the URL holds credentials (user:password@), which are not used (and are \
                    left out of messages): give a bearer token with BRICKYARD_TOKEN instead"
                .to_string(),
        );
    }
    if let Some(q) = url.find(['?', '#']) {
        let what = if url[q..].starts_with('?') {
            "a query string"
        } else {
            "a fragment"
        };
        let token = if what == "a query string" {
            " (give a token with BRICKYARD_TOKEN instead of ?token=…)"
        } else {
            ""
        };
        return Err(format!(
            "the URL holds {what} ({:?}): a store URL must end in the store's path, since keys \
             are joined onto it; remove it{token}",
            &redact(url)[q..]
        ));
    }
    let host_port = auth.rsplit('@').next().unwrap_or(auth);
    let port = match host_port.strip_prefix('[') {
        Some(v6) => v6.split_once(']').map_or("", |(_, p)| p),
        None => host_port.rsplit_once(':').map_or("", |(_, p)| p),
    };
    if let Some(p) = port
        .strip_prefix(':')
        .or((!port.is_empty()).then_some(port))
    {
        if !p.is_empty() && !p.parse::<u16>().is_ok_and(|n| n > 0) {
            return Err(format!(
                "invalid port {p:?} in the URL (a port is a number from 1 to 65535)"
            ));
        }
    }
    Ok(())
}

/// The `ETag` of an answer.
fn etag_of(resp: &ureq::http::Response<ureq::Body>) -> Option<String> {
    resp.headers()
        .get("etag")
        .and_then(|v| v.to_str().ok())
        .map(|v| v.trim().to_string())
        .filter(|v| !v.is_empty())
}

/// Whether two ETags name the same version (weak comparison).
fn same_etag(a: &str, b: &str) -> bool {
    a.trim_start_matches("W/") == b.trim_start_matches("W/")
}

/// Where the values of the array holding `url` lie: the URL up to its
/// chunk keys' `/c/` (Zarr v3's default key encoding), else its folder.
fn array_prefix(url: &str) -> &str {
    match url.rfind("/c/") {
        Some(i) => &url[..i + 1],
        None => &url[..url.rfind('/').map_or(url.len(), |i| i + 1)],
    }
}

/// How long the failure of a read (after its retries) is remembered for
/// its file: meanwhile a read of that file tries once, without retries,
/// and fails at once while another read of it is under way.
const FAILING_FOR: Duration = Duration::from_secs(30);
/// How long a metadata document read is used without asking the server
/// whether it changed (`If-None-Match`): a store opened again later sees
/// the store as it is then.
const META_FRESH: Duration = Duration::from_secs(1);
/// How long a file the server said is not there (404, 410) is taken as
/// absent without asking again: every brick of a missing shard asked for
/// it (a render of a store missing one shard sent 995 HEADs and 770
/// GETs for it, and took 30 s).
const ABSENT_FRESH: Duration = Duration::from_secs(10);
/// Most files whose ETag is remembered (the set is cleared past this).
const PINS_MAX: usize = 1 << 16;

/// A file whose reads failed after all their retries.
struct Failing {
    /// What happened, with the number of attempts.
    what: String,
    since: Instant,
    last: Instant,
    /// The one attempt at it under way, which other reads wait for.
    probe: Option<Arc<Probe>>,
}

/// How one attempt at a failing file ended (`Some(None)`: it was read,
/// `Some(Some((what, retry)))`: it failed so, with a failure worth
/// retrying or not).
#[derive(Default)]
struct Probe {
    done: Mutex<Option<Option<(String, bool)>>>,
    cv: Condvar,
}

/// The attempt of a read at a failing file: tells the reads waiting for
/// it how it ended, also should it panic.
struct ProbeGuard(Arc<Probe>);

impl ProbeGuard {
    fn land(self, what: Option<(String, bool)>) {
        *self.0.done.lock().unwrap_or_else(|e| e.into_inner()) = Some(what);
    }
}

impl Drop for ProbeGuard {
    fn drop(&mut self) {
        let mut done = self.0.done.lock().unwrap_or_else(|e| e.into_inner());
        if done.is_none() {
            *done = Some(Some(("the read failed".to_string(), true)));
        }
        self.0.cv.notify_all();
    }
}

/// The result of a shard index read that other readers of the same index
/// wait for (`Err`: the message, without the URL).
type Shared = std::result::Result<Option<Suffix>, String>;

#[derive(Default)]
struct Flight {
    done: Mutex<Option<Shared>>,
    cv: Condvar,
}

/// The HTTP client of remote stores.
pub struct Client {
    cfg: HttpConfig,
    agent: ureq::Agent,
    slots: Slots,
    indexes: Mutex<IndexCache>,
    requests: AtomicU64,
    retries: AtomicU64,
    failures: AtomicU64,
    bytes: AtomicU64,
    index_hits: AtomicU64,
    seed: AtomicU64,
    /// Metadata documents (`zarr.json`, `.zarray`, …) and whether they
    /// exist, with their ETags: used for [`META_FRESH`], then asked for
    /// again conditionally.
    meta: Mutex<MetaCache>,
    /// Hosts by `scheme://host:port`.
    hosts: Mutex<HashMap<String, HostHealth>>,
    /// The ETag of each file whose index (or size) was read: its range
    /// reads, which use offsets from that index, are sent with
    /// `If-Match`, so that a file replaced on the server is not read at
    /// the old offsets.
    pins: Mutex<HashMap<String, String>>,
    /// Files whose reads failed after all their retries, by URL.
    failing: Mutex<HashMap<String, Failing>>,
    /// Shard index reads under way: readers of the same index wait for
    /// the one read and take its result.
    flights: Mutex<HashMap<(String, u64), Arc<Flight>>>,
    /// Hosts (`scheme://host:port`) whose TLS handshake failed, with why
    /// and when: their requests fail at once for [`FAILING_FOR`] (a plain
    /// HTTP server asked with https:// would cost every document read
    /// the handshake's timeout).
    tls_failed: Mutex<HashMap<String, (String, Instant)>>,
    /// Files (not metadata documents) the server said are not there, and
    /// when ([`ABSENT_FRESH`]).
    absent: Mutex<HashMap<String, Instant>>,
}

/// A metadata document (`None`: not there), its ETag and when the server
/// last said it was current.
struct MetaEntry {
    doc: Option<Arc<Vec<u8>>>,
    etag: Option<String>,
    checked: Instant,
}

/// Whole metadata documents by URL, bounded in bytes.
#[derive(Default)]
struct MetaCache {
    map: HashMap<String, MetaEntry>,
    bytes: usize,
}

impl MetaCache {
    fn remove_if(&mut self, f: impl Fn(&str) -> bool) {
        let mut freed = 0;
        self.map.retain(|k, e| {
            let keep = !f(k);
            if !keep {
                freed += e.doc.as_ref().map_or(0, |d| d.len());
            }
            keep
        });
        self.bytes -= freed;
    }
}

/// Most bytes of metadata documents kept.
const META_CACHE_BYTES: usize = 16 << 20;
/// Largest document kept.
const META_MAX: usize = 1 << 20;

/// Whether `url` names a metadata document of a Zarr store.
fn is_meta(url: &str) -> bool {
    let name = url.rsplit('/').next().unwrap_or("");
    matches!(
        name,
        "zarr.json" | ".zarray" | ".zattrs" | ".zgroup" | ".zmetadata"
    )
}

fn status_text(code: u16) -> &'static str {
    match code {
        400 => "Bad Request",
        401 => "Unauthorized",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        416 => "Range Not Satisfiable",
        429 => "Too Many Requests",
        500 => "Internal Server Error",
        502 => "Bad Gateway",
        503 => "Service Unavailable",
        504 => "Gateway Timeout",
        _ => "",
    }
}

/// `Content-Range: bytes a-b/len` → `(a, b + 1, len)` (`len` `None` for `*`).
fn content_range(v: &str) -> Option<(u64, u64, Option<u64>)> {
    let v = v.trim().strip_prefix("bytes ")?;
    let (r, len) = v.split_once('/')?;
    let (a, b) = r.split_once('-')?;
    let a: u64 = a.trim().parse().ok()?;
    let b: u64 = b.trim().parse().ok()?;
    (a <= b).then_some(())?;
    Some((a, b + 1, len.trim().parse().ok()))
}

impl Client {
    pub fn new(cfg: HttpConfig) -> Self {
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(cfg.timeout))
            .timeout_connect(Some(cfg.connect_timeout))
            .timeout_recv_response(Some(cfg.response_timeout).filter(|t| *t < cfg.timeout))
            .max_redirects(4)
            .max_idle_connections_per_host(cfg.max_in_flight.max(1))
            .build()
            .new_agent();
        Client {
            slots: Slots {
                free: Mutex::new(cfg.max_in_flight.max(1)),
                cv: Condvar::new(),
            },
            agent,
            cfg,
            indexes: Mutex::new(IndexCache::default()),
            requests: AtomicU64::new(0),
            retries: AtomicU64::new(0),
            failures: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
            index_hits: AtomicU64::new(0),
            seed: AtomicU64::new(0x9e37_79b9_7f4a_7c15),
            meta: Mutex::new(MetaCache::default()),
            hosts: Mutex::new(HashMap::new()),
            pins: Mutex::new(HashMap::new()),
            failing: Mutex::new(HashMap::new()),
            flights: Mutex::new(HashMap::new()),
            tls_failed: Mutex::new(HashMap::new()),
            absent: Mutex::new(HashMap::new()),
        }
    }

    /// Whether the server said lately that `url` is not there.
    fn known_absent(&self, url: &str) -> bool {
        let mut a = self.absent.lock().unwrap_or_else(|e| e.into_inner());
        match a.get(url) {
            Some(t) if t.elapsed() < ABSENT_FRESH => true,
            Some(_) => {
                a.remove(url);
                false
            }
            None => false,
        }
    }

    /// `got` of a read of `url`, remembered when it says the file is not
    /// there (the map keeps at most 4096 such files).
    fn note_absent<T>(&self, url: &str, got: &Result<Option<T>, impl Sized>) {
        if let Ok(None) = got {
            let mut a = self.absent.lock().unwrap_or_else(|e| e.into_inner());
            if a.len() >= 4096 {
                a.retain(|_, t| t.elapsed() < ABSENT_FRESH);
                if a.len() >= 4096 {
                    a.clear();
                }
            }
            a.insert(url.to_string(), Instant::now());
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &HttpConfig {
        &self.cfg
    }

    /// The size of the value at `url` (a HEAD request); `None` on 404.
    pub fn size(&self, url: &str) -> Result<Option<u64>> {
        if is_meta(url) {
            // A metadata document is read whole: its length with it.
            return Ok(self.meta_doc(url)?.map(|d| d.len() as u64));
        }
        if self.known_absent(url) {
            return Ok(None);
        }
        let got = self.with_retries(url, "HEAD", None, None, |resp| {
            let len = resp
                .headers()
                .get("content-length")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().parse::<u64>().ok());
            let len = len.ok_or_else(|| Failure::fatal("the answer has no Content-Length"))?;
            Ok((len, etag_of(resp)))
        });
        self.note_absent(url, &got);
        Ok(got?.map(|(len, etag)| {
            if let Some(e) = etag {
                self.saw_version(url, e);
            }
            len
        }))
    }

    /// A size read (`HEAD`) of `url` answered with `etag`: where an index
    /// of another version was read, the file changed; what was cached of
    /// it goes, and its reads keep the ETag of the index their offsets
    /// came from (they fail until the index is read again, which pins the
    /// new version). Taking the new ETag here sent reads at the old
    /// index's offsets with the new version's `If-Match`: the server
    /// served them, and the old offsets read the new file's bytes.
    fn saw_version(&self, url: &str, etag: String) {
        let pins = self.pins.lock().unwrap_or_else(|e| e.into_inner());
        match pins.get(url) {
            Some(old) if !same_etag(old, &etag) => {
                drop(pins);
                self.forget(url);
            }
            Some(_) => {}
            None => {
                drop(pins);
                self.pin(url, etag);
            }
        }
    }

    /// An error of a read of `url` (shown without credentials or query).
    fn error(&self, url: &str, what: String) -> StoreError {
        StoreError::io(redact(url), std::io::Error::other(what))
    }

    /// Remember `etag` as the version of `url` whose index (or size) was
    /// read; a different one than remembered means the file changed: what
    /// was cached of it and of its store is dropped.
    fn pin(&self, url: &str, etag: String) {
        let mut pins = self.pins.lock().unwrap_or_else(|e| e.into_inner());
        let changed = pins.get(url).is_some_and(|old| !same_etag(old, &etag));
        if pins.len() >= PINS_MAX && !pins.contains_key(url) {
            pins.clear();
        }
        pins.insert(url.to_string(), etag);
        drop(pins);
        if changed {
            self.forget(url);
        }
    }

    /// The file at `url` changed on the server: drop the cached indexes of
    /// its array (the others were most likely replaced with it) and the
    /// metadata documents, so that a store opened again reads them anew.
    /// Its ETag stays remembered: reads at offsets from its old index keep
    /// failing until the index is read again.
    fn forget(&self, url: &str) {
        let prefix = array_prefix(url);
        self.indexes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove_if(|u| u == url || u.starts_with(prefix));
        let host = host_of(url);
        self.meta
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove_if(|u| host_of(u) == host);
    }

    /// The metadata document at `url`: from the cache while it was
    /// checked less than [`META_FRESH`] ago, else asked for again (with
    /// `If-None-Match` where it has an ETag: a 304 keeps it).
    fn meta_doc(&self, url: &str) -> Result<Option<Arc<Vec<u8>>>> {
        let cached = {
            let m = self.meta.lock().unwrap_or_else(|e| e.into_inner());
            m.map.get(url).map(|e| {
                (
                    e.doc.clone(),
                    e.etag.clone(),
                    e.checked.elapsed() < META_FRESH,
                )
            })
        };
        if let Some((doc, _, true)) = &cached {
            self.index_hits.fetch_add(1, Ordering::Relaxed);
            return Ok(doc.clone());
        }
        enum Got {
            NotModified,
            Doc(Vec<u8>, Option<String>),
        }
        let cond = cached
            .as_ref()
            .and_then(|(d, e, _)| d.as_ref().and(e.clone()))
            .map(|e| ("If-None-Match", e));
        let got = self.with_retries(url, "GET", None, cond, |resp| {
            if resp.status().as_u16() == 304 {
                return Ok(Got::NotModified);
            }
            let etag = etag_of(resp);
            Ok(Got::Doc(read_body(resp, &Span::All)?, etag))
        })?;
        let (doc, etag) = match got {
            Some(Got::NotModified) => {
                let mut m = self.meta.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(e) = m.map.get_mut(url) {
                    e.checked = Instant::now();
                }
                self.index_hits.fetch_add(1, Ordering::Relaxed);
                return Ok(cached.and_then(|(d, _, _)| d));
            }
            Some(Got::Doc(d, etag)) => {
                self.bytes.fetch_add(d.len() as u64, Ordering::Relaxed);
                (Some(Arc::new(d)), etag)
            }
            None => (None, None),
        };
        // A document that changed: the store (or this array) was
        // replaced; what was cached under it is stale.
        if let Some((old, _, _)) = &cached {
            if old.as_deref() != doc.as_deref() {
                let dir = &url[..url.rfind('/').map_or(url.len(), |i| i + 1)];
                self.indexes
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .remove_if(|u| u.starts_with(dir));
                self.meta
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .remove_if(|u| u.starts_with(dir));
            }
        }
        let size = doc.as_ref().map_or(0, |d| d.len());
        let mut m = self.meta.lock().unwrap_or_else(|e| e.into_inner());
        m.remove_if(|u| u == url);
        if size <= META_MAX && m.bytes + size <= META_CACHE_BYTES {
            m.bytes += size;
            m.map.insert(
                url.to_string(),
                MetaEntry {
                    doc: doc.clone(),
                    etag,
                    checked: Instant::now(),
                },
            );
        }
        Ok(doc)
    }

    /// Read `spans` of the value at `url` (see [`super::read_spans`]).
    pub fn read_spans(&self, url: &str, spans: &[Span]) -> Result<Option<Vec<Vec<u8>>>> {
        if is_meta(url) {
            let Some(doc) = self.meta_doc(url)? else {
                return Ok(None);
            };
            let len = doc.len() as u64;
            return spans
                .iter()
                .map(|s| {
                    let r = match s {
                        Span::Suffix(n) => len.saturating_sub(*n)..len,
                        s => s.within(len).ok_or_else(|| {
                            self.error(
                                url,
                                format!("bytes {s:?} asked for, but the value holds {len}"),
                            )
                        })?,
                    };
                    Ok(doc[r.start as usize..r.end as usize].to_vec())
                })
                .collect::<Result<Vec<_>>>()
                .map(Some);
        }
        let mut out: Vec<Option<Vec<u8>>> = vec![None; spans.len()];
        // Byte ranges, coalesced: sorted, then merged while the gap
        // between neighbours is small and the merged read stays bounded.
        let mut ranges: Vec<(usize, std::ops::Range<u64>)> = spans
            .iter()
            .enumerate()
            .filter_map(|(i, s)| match s {
                Span::Range(r) => Some((i, r.clone())),
                _ => None,
            })
            .collect();
        ranges.sort_by_key(|(_, r)| (r.start, r.end));
        let mut k = 0;
        while k < ranges.len() {
            let start = ranges[k].1.start;
            let mut end = ranges[k].1.end;
            let mut m = k + 1;
            while m < ranges.len()
                && ranges[m].1.start <= end.saturating_add(self.cfg.coalesce_gap)
                && ranges[m].1.end.max(end) - start <= COALESCE_MAX
            {
                end = end.max(ranges[m].1.end);
                m += 1;
            }
            let Some(bytes) = self.get(url, &Span::Range(start..end))? else {
                return Ok(None);
            };
            for (i, r) in &ranges[k..m] {
                out[*i] =
                    Some(bytes[(r.start - start) as usize..(r.end - start) as usize].to_vec());
            }
            k = m;
        }
        for (i, s) in spans.iter().enumerate() {
            if out[i].is_some() {
                continue;
            }
            let got = match s {
                Span::Suffix(n) => self.suffix(url, *n)?.map(|(b, _)| b.to_vec()),
                _ => self.get(url, s)?,
            };
            let Some(b) = got else {
                return Ok(None);
            };
            out[i] = Some(b);
        }
        Ok(Some(
            out.into_iter().map(Option::unwrap_or_default).collect(),
        ))
    }

    /// The last `n` bytes of the value at `url` (fewer when it is shorter)
    /// and the value's length, from one ranged GET (the length is in the
    /// answer's `Content-Range`), cached: a shard's index and size without
    /// a HEAD request. `None` on 404. Readers of an index being read wait
    /// for that read and share its result, a failure included.
    pub fn suffix(&self, url: &str, n: u64) -> Result<Option<(Arc<Vec<u8>>, u64)>> {
        let key = (url.to_string(), n);
        let hit = || {
            self.indexes
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .map
                .get(&key)
                .cloned()
        };
        if let Some(h) = hit() {
            self.index_hits.fetch_add(1, Ordering::Relaxed);
            return Ok(Some(h));
        }
        if self.known_absent(url) {
            return Ok(None);
        }
        if n == 0 {
            return Ok(self.size(url)?.map(|len| (Arc::new(vec![]), len)));
        }
        let (flight, leader) = {
            let mut f = self.flights.lock().unwrap_or_else(|e| e.into_inner());
            match f.get(&key) {
                Some(fl) => (fl.clone(), false),
                None => {
                    let fl = Arc::new(Flight::default());
                    f.insert(key.clone(), fl.clone());
                    (fl, true)
                }
            }
        };
        if !leader {
            let mut done = flight.done.lock().unwrap_or_else(|e| e.into_inner());
            while done.is_none() {
                done = flight.cv.wait(done).unwrap_or_else(|e| e.into_inner());
            }
            if let Some(Ok(Some(_))) = done.as_ref() {
                self.index_hits.fetch_add(1, Ordering::Relaxed);
            }
            return done.clone().unwrap().map_err(|m| self.error(url, m));
        }
        // The waiters get the result, or an error should this read panic.
        struct Land<'a>(&'a Client, &'a (String, u64), &'a Flight);
        impl Drop for Land<'_> {
            fn drop(&mut self) {
                let mut done = self.2.done.lock().unwrap_or_else(|e| e.into_inner());
                if done.is_none() {
                    *done = Some(Err("the read of this index failed".to_string()));
                }
                self.2.cv.notify_all();
                drop(done);
                self.0
                    .flights
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .remove(self.1);
            }
        }
        let _land = Land(self, &key, &flight);
        // (Another read may have finished between the look-up and now.)
        let res = match hit() {
            Some(h) => Ok(Some(h)),
            None => self.read_suffix(url, n),
        };
        self.note_absent(url, &res);
        *flight.done.lock().unwrap_or_else(|e| e.into_inner()) = Some(res.clone());
        res.map_err(|m| self.error(url, m))
    }

    /// The read of [`suffix`](Self::suffix): errors without the URL.
    fn read_suffix(&self, url: &str, n: u64) -> Shared {
        let range = format!("bytes=-{n}");
        let got = self.attempts(url, "GET", Some(&range), None, |resp| {
            let header = |k: &str| {
                resp.headers()
                    .get(k)
                    .and_then(|v| v.to_str().ok())
                    .map(str::to_string)
            };
            // 206: `bytes a-b/len`; 200 (Range ignored): the whole value.
            let total = if resp.status().as_u16() == 206 {
                header("content-range")
                    .as_deref()
                    .and_then(content_range)
                    .and_then(|(_, _, len)| len)
            } else {
                header("content-length").and_then(|v| v.trim().parse().ok())
            };
            let etag = etag_of(resp);
            let body = read_body(resp, &Span::Suffix(n))?;
            Ok((body, total, etag))
        });
        // (A value shorter than `n` comes whole, as HTTP says for suffix
        // ranges; an empty one gets 416, an error naming the URL.)
        let Some((body, total, etag)) = got? else {
            return Ok(None);
        };
        self.bytes.fetch_add(body.len() as u64, Ordering::Relaxed);
        if let Some(e) = etag {
            self.pin(url, e);
        }
        let len = match total {
            Some(t) => t,
            // No length in the answer: ask for it.
            None => match self.size(url) {
                Ok(Some(t)) => t,
                Ok(None) => return Ok(None),
                Err(e) => return Err(e.to_string()),
            },
        };
        let body = Arc::new(body);
        self.indexes.lock().unwrap_or_else(|e| e.into_inner()).put(
            (url.to_string(), n),
            body.clone(),
            len,
        );
        Ok(Some((body, len)))
    }

    /// GET one span; `None` on 404. A range of a file whose index was
    /// read (an ETag remembered) is asked for with `If-Match`, and an
    /// answer of another version is refused: the offsets came from the
    /// index of the version remembered.
    fn get(&self, url: &str, span: &Span) -> Result<Option<Vec<u8>>> {
        if let Span::Range(r) = span {
            if r.start >= r.end {
                return Ok(Some(vec![]));
            }
        }
        let range = match span {
            Span::All => None,
            Span::Range(r) => Some(format!("bytes={}-{}", r.start, r.end - 1)),
            Span::From(o) => Some(format!("bytes={o}-")),
            Span::Suffix(0) => return Ok(Some(vec![])),
            Span::Suffix(n) => Some(format!("bytes=-{n}")),
        };
        let pin = match span {
            Span::Range(_) | Span::From(_) => self
                .pins
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(url)
                .cloned(),
            _ => None,
        };
        // `If-Match` compares strongly: a weak ETag never matches.
        let cond = pin
            .as_ref()
            .filter(|e| !e.starts_with("W/"))
            .map(|e| ("If-Match", e.clone()));
        let got = self.with_retries(url, "GET", range.as_deref(), cond, |resp| {
            if let (Some(p), Some(e)) = (&pin, etag_of(resp)) {
                if !same_etag(p, &e) {
                    return Err(Failure::changed());
                }
            }
            read_body(resp, span)
        })?;
        if let Some(b) = &got {
            self.bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
        }
        Ok(got)
    }

    /// One request with retries: `Ok(None)` on 404, the value `take` makes
    /// of a 200/206 (or, asked conditionally, 304) answer otherwise.
    fn with_retries<T>(
        &self,
        url: &str,
        method: &str,
        range: Option<&str>,
        cond: Option<(&'static str, String)>,
        take: impl Fn(&mut ureq::http::Response<ureq::Body>) -> std::result::Result<T, Failure>,
    ) -> Result<Option<T>> {
        self.attempts(url, method, range, cond, take)
            .map_err(|m| self.error(url, m))
    }

    /// [`with_retries`](Self::with_retries), its error without the URL.
    /// A file whose reads failed after all their retries less than
    /// [`FAILING_FOR`] ago is tried once, not on the whole schedule; reads
    /// of it while that one attempt is under way wait for it and fail as
    /// it did (or, if it succeeded, go on): every brick of a shard that
    /// keeps failing fails fast.
    fn attempts<T>(
        &self,
        url: &str,
        method: &str,
        range: Option<&str>,
        cond: Option<(&'static str, String)>,
        take: impl Fn(&mut ureq::http::Response<ureq::Body>) -> std::result::Result<T, Failure>,
    ) -> std::result::Result<Option<T>, String> {
        let bytes = range.map(|r| format!(" ({r})")).unwrap_or_default();
        if let Err(why) = check_url(url) {
            return Err(format!("{method}: {why}"));
        }
        if let Some((why, at)) = self
            .tls_failed
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(host_of(url))
            .filter(|(_, at)| at.elapsed() < FAILING_FOR)
        {
            return Err(format!(
                "{method}{bytes}: {why} (found {:.0} s ago; not tried again)",
                at.elapsed().as_secs_f64()
            ));
        }
        let mut retries = self.cfg.retries;
        // Reads of this file failed a while ago: (first failure, for how
        // long), and the one attempt this read makes for the others.
        let mut earlier: Option<(String, Duration)> = None;
        let mut ours: Option<ProbeGuard> = None;
        let theirs = {
            let mut failing = self.failing.lock().unwrap_or_else(|e| e.into_inner());
            match failing.get_mut(url) {
                Some(f) if f.last.elapsed() >= FAILING_FOR => {
                    failing.remove(url);
                    None
                }
                Some(f) => match &f.probe {
                    Some(p) => Some((p.clone(), f.what.clone(), f.since.elapsed())),
                    None => {
                        let p = Arc::new(Probe::default());
                        f.probe = Some(p.clone());
                        ours = Some(ProbeGuard(p));
                        retries = 0;
                        earlier = Some((f.what.clone(), f.since.elapsed()));
                        None
                    }
                },
                None => None,
            }
        };
        if let Some((p, first, for_)) = theirs {
            let mut done = p.done.lock().unwrap_or_else(|e| e.into_inner());
            while done.is_none() {
                done = p.cv.wait(done).unwrap_or_else(|e| e.into_inner());
            }
            if let Some(Some((what, retry))) = done.as_ref() {
                self.failures.fetch_add(1, Ordering::Relaxed);
                if !retry {
                    // Another kind of failure (access refused, a changed
                    // file): as the read would have failed itself.
                    return Err(format!("{method}{bytes}: {what}"));
                }
                return Err(format!(
                    "{method}{bytes}: {what}; not tried, as a read of this file just failed so \
                     (its reads have failed for {:.0} s: {first})",
                    for_.as_secs_f64().ceil()
                ));
            }
            // It succeeded: read as usual.
        }
        let mut attempt = 0u32;
        loop {
            let res = match self.host_down(url) {
                Some(why) => Err(Failure::fatal(why)),
                None => {
                    let _permit = self.slots.acquire();
                    self.requests.fetch_add(1, Ordering::Relaxed);
                    let r = self.once(url, method, range, cond.as_ref(), &take);
                    self.host_seen(url, r.as_ref().err());
                    r
                }
            };
            match res {
                Ok(v) => {
                    if let Some(g) = ours.take() {
                        self.failing
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .remove(url);
                        g.land(None);
                    }
                    return Ok(v);
                }
                Err(f) if f.retry && attempt < retries.min(f.most_retries) => {
                    self.retries.fetch_add(1, Ordering::Relaxed);
                    std::thread::sleep(self.backoff(attempt));
                    attempt += 1;
                }
                Err(f) => {
                    self.failures.fetch_add(1, Ordering::Relaxed);
                    if f.changed {
                        self.forget(url);
                    }
                    let tries = if attempt > 0 {
                        format!(", after {} attempts", attempt + 1)
                    } else {
                        String::new()
                    };
                    let msg = match &earlier {
                        Some((first, for_)) if f.retry => format!(
                            "{method}{bytes}: {}; tried once, as reads of this file have failed \
                             for {:.0} s ({first})",
                            f.what,
                            for_.as_secs_f64().ceil()
                        ),
                        _ => format!("{method}{bytes}: {}{tries}", f.what),
                    };
                    let mut failing = self.failing.lock().unwrap_or_else(|e| e.into_inner());
                    if f.retry {
                        let now = Instant::now();
                        let e = failing.entry(url.to_string()).or_insert(Failing {
                            what: format!("{}{tries}", f.what),
                            since: now,
                            last: now,
                            probe: None,
                        });
                        e.last = now;
                        if ours.is_some() {
                            e.probe = None;
                        }
                    } else if ours.is_some() {
                        failing.remove(url);
                    }
                    drop(failing);
                    if let Some(g) = ours.take() {
                        g.land(Some((f.what.clone(), f.retry)));
                    }
                    return Err(msg);
                }
            }
        }
    }

    /// Why requests to `url`'s host fail without trying, if they do.
    /// After its pause, one attempt goes out (the caller's) and the others
    /// fail until it ends.
    fn host_down(&self, url: &str) -> Option<String> {
        let mut hosts = self.hosts.lock().unwrap_or_else(|e| e.into_inner());
        let h = hosts.get_mut(host_of(url))?;
        let now = Instant::now();
        let until = h.down_until?;
        let then = match until.checked_duration_since(now) {
            Some(left) => format!(
                "requests to it fail without trying for {:.0} s more",
                left.as_secs_f64().ceil()
            ),
            // (An attempt that never said how it ended, e.g. one whose
            // thread panicked, holds the others back at most a timeout.)
            None if h
                .probe_since
                .is_some_and(|t| now.duration_since(t) < self.cfg.timeout) =>
            {
                "one request is trying it again; the others fail without trying meanwhile"
                    .to_string()
            }
            None => {
                h.probe_since = Some(now);
                return None;
            }
        };
        Some(format!(
            "not sent: {} is not answering: attempts in a row got no connection or no answer \
             (last: {}); {then}",
            redact(host_of(url)),
            h.last,
        ))
    }

    /// Note how an attempt on `url` ended (`None`: it succeeded).
    fn host_seen(&self, url: &str, failure: Option<&Failure>) {
        let mut hosts = self.hosts.lock().unwrap_or_else(|e| e.into_inner());
        match failure {
            Some(f) if f.unreachable => {
                let h = hosts.entry(host_of(url).to_string()).or_default();
                h.fails_in_a_row += if f.silence { SILENCE_COUNTS } else { 1 };
                // (Which request: a request refused meanwhile is named, and
                // a zarr.json the server had answered read as the fault.)
                h.last = format!("{}: {}", redact(url), f.what);
                h.probe_since = None;
                if h.fails_in_a_row >= HOST_DOWN_AFTER {
                    h.pause = if h.down_until.is_some() {
                        (h.pause * 2).min(HOST_PAUSE_MAX)
                    } else {
                        HOST_PAUSE
                    };
                    h.down_until = Some(Instant::now() + h.pause);
                }
            }
            // An answer: the host is there.
            _ => {
                hosts.remove(host_of(url));
            }
        }
    }

    fn backoff(&self, attempt: u32) -> Duration {
        let base = self
            .cfg
            .backoff
            .saturating_mul(1 << attempt.min(16))
            .min(BACKOFF_MAX);
        // xorshift jitter: up to a quarter more.
        let mut x = self
            .seed
            .fetch_add(0x9e37_79b9_7f4a_7c15, Ordering::Relaxed);
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        base + base.mul_f64((x % 1000) as f64 / 4000.0)
    }

    fn once<T>(
        &self,
        url: &str,
        method: &str,
        range: Option<&str>,
        cond: Option<&(&'static str, String)>,
        take: &impl Fn(&mut ureq::http::Response<ureq::Body>) -> std::result::Result<T, Failure>,
    ) -> std::result::Result<Option<T>, Failure> {
        // An s3:// location is signed for this attempt (the signature
        // holds the time); its token is not a bearer token.
        let s3 = super::s3::is_s3(url);
        let signed;
        let given = url;
        let (url, token) = if s3 {
            signed = super::s3::request_url(url, method).map_err(Failure::fatal)?;
            (signed.as_str(), None)
        } else {
            (url, self.cfg.token.as_ref())
        };
        if let Some(why) = token.and_then(|t| token_problem(t)) {
            return Err(Failure::fatal(why));
        }
        let call = if method == "HEAD" {
            let mut rq = self.agent.head(url);
            if let Some(t) = token {
                rq = rq.header("Authorization", format!("Bearer {t}"));
            }
            rq.call()
        } else {
            let mut rq = self.agent.get(url);
            if let Some(r) = range {
                rq = rq.header("Range", r);
            }
            if let Some((k, v)) = cond {
                rq = rq.header(*k, v.as_str());
            }
            if let Some(t) = token {
                rq = rq.header("Authorization", format!("Bearer {t}"));
            }
            rq.call()
        };
        let mut resp = call.map_err(|e| self.classify(given, e))?;
        let code = resp.status().as_u16();
        match code {
            200 | 206 => take(&mut resp).map(Some),
            // Only asked for conditionally (`If-None-Match`).
            304 if cond.is_some() => take(&mut resp).map(Some),
            404 | 410 => Ok(None),
            // `If-Match` failed: another version of the file is there.
            412 if cond.is_some_and(|(k, _)| *k == "If-Match") => Err(Failure::changed()),
            401 | 403 => Err(Failure::fatal(format!(
                "HTTP {code} {}: access refused{}",
                status_text(code),
                // The server's own reason, where it gives one in a short
                // line of text (a refused path is not a missing token).
                if let Some(why) = (!s3).then(|| short_reason(&mut resp)).flatten() {
                    match (code, self.cfg.token.is_some()) {
                        (401, false) => format!(": {why} (set BRICKYARD_TOKEN)"),
                        // (A wrong token read as a missing one.)
                        (401, true) => {
                            format!(": {why} (the token given was refused: check BRICKYARD_TOKEN)")
                        }
                        _ => format!(": {why}"),
                    }
                } else if s3 {
                    if super::s3::signed() {
                        " (the signed request was refused: check AWS_ACCESS_KEY_ID, \
                         AWS_SECRET_ACCESS_KEY, AWS_SESSION_TOKEN and AWS_REGION; \
                         S3 also answers 403 for a missing key without list permission)"
                            .to_string()
                    } else {
                        " (an unsigned request: set AWS_ACCESS_KEY_ID and \
                         AWS_SECRET_ACCESS_KEY for a private bucket)"
                            .to_string()
                    }
                } else if self.cfg.token.is_some() {
                    " (the bearer token was not accepted)".into()
                } else if code == 401 {
                    " (a token is needed: set BRICKYARD_TOKEN)".into()
                } else {
                    " (the server refuses this path; if it takes tokens, set BRICKYARD_TOKEN)"
                        .into()
                }
            ))),
            // A gateway that cannot reach the server behind it: as good
            // as nobody there (a proxy whose backend died answers every
            // request so).
            502 | 504 => Err(Failure::unreachable(format!(
                "HTTP {code} {} (the server behind a proxy or gateway did not answer)",
                status_text(code)
            ))),
            408 | 429 | 500..=599 => {
                Err(Failure::retry(format!("HTTP {code} {}", status_text(code))))
            }
            _ => Err(Failure::fatal(format!("HTTP {code} {}", status_text(code)))),
        }
    }

    /// Whether `url` is `https://` and a TCP connection to its host and
    /// port can be made now (within the connect timeout, at most 1 s):
    /// then a connect that timed out or failed did so in the TLS handshake.
    fn tcp_connects(&self, url: &str) -> bool {
        use std::net::ToSocketAddrs;
        if !url.get(..8).unwrap_or("").eq_ignore_ascii_case("https://") {
            return false;
        }
        let auth = authority(url);
        let hp = auth.rsplit('@').next().unwrap_or(auth);
        let has_port = match hp.rfind(']') {
            Some(b) => hp[b..].contains(':'),
            None => hp.contains(':'),
        };
        let target = if has_port {
            hp.to_string()
        } else {
            format!("{hp}:443")
        };
        let wait = self.cfg.connect_timeout.min(Duration::from_secs(1));
        let Ok(addrs) = target.to_socket_addrs() else {
            return false;
        };
        addrs
            .into_iter()
            .any(|a| std::net::TcpStream::connect_timeout(&a, wait).is_ok())
    }

    fn classify(&self, url: &str, e: ureq::Error) -> Failure {
        let f = self.classify_error(url, e);
        if f.what.contains("the TLS handshake") {
            self.tls_failed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(host_of(url).to_string(), (f.what.clone(), Instant::now()));
        }
        f
    }

    fn classify_error(&self, url: &str, e: ureq::Error) -> Failure {
        const PLAIN: &str = "is it a plain-HTTP server? then use http:// instead of https://";
        match e {
            ureq::Error::Timeout(ureq::Timeout::Connect) if self.tcp_connects(url) => {
                Failure::fatal(format!(
                    "the TLS handshake did not finish within {:.1} s (the server accepts \
                     connections but does not answer TLS): {PLAIN}",
                    self.cfg.connect_timeout.as_secs_f64()
                ))
            }
            ureq::Error::Timeout(t @ (ureq::Timeout::Connect | ureq::Timeout::Resolve)) => {
                Failure::unreachable(format!(
                    "timed out ({t}) after at most {:.1} s",
                    self.cfg.connect_timeout.as_secs_f64()
                ))
            }
            // Connected, asked, and no answer: as good as nobody there.
            ureq::Error::Timeout(t @ ureq::Timeout::RecvResponse) => Failure {
                most_retries: 1,
                silence: true,
                ..Failure::unreachable(format!(
                    "no answer ({t}) within {:.1} s",
                    self.cfg.response_timeout.as_secs_f64()
                ))
            },
            ureq::Error::Timeout(t) => Failure::retry(format!(
                "timed out ({t}) after at most {:.1} s",
                self.cfg.timeout.as_secs_f64()
            )),
            ureq::Error::HostNotFound => Failure::fatal("host not found"),
            ureq::Error::BadUri(u) => Failure::fatal(format!("not a valid URL: {}", redact(&u))),
            ureq::Error::ConnectionFailed => Failure::unreachable("connection failed"),
            ureq::Error::Io(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::ConnectionRefused
                        | std::io::ErrorKind::HostUnreachable
                        | std::io::ErrorKind::NetworkUnreachable
                        | std::io::ErrorKind::AddrNotAvailable
                ) =>
            {
                Failure::unreachable(format!("connection error: {e}"))
            }
            // A reset or close during the handshake of a server that
            // answered the TLS greeting as if it were HTTP.
            ureq::Error::Io(e) if self.tls_phase(url, &e.to_string()) => Failure::fatal(format!(
                "the TLS handshake failed (connection error: {e}): {PLAIN}"
            )),
            ureq::Error::Io(e) => Failure::retry(format!("connection error: {e}")),
            ureq::Error::BodyStalled => Failure::retry("the body stalled"),
            ureq::Error::Http(e) => Failure::fatal(format!("invalid request: {e}")),
            e @ ureq::Error::Protocol(_) => Failure::retry(format!("protocol error: {e}")),
            e => {
                let s = e.to_string();
                let tls = s.contains("TLS") || s.contains("tls") || s.contains("rustls");
                if tls && (s.contains("corrupt message") || s.contains("InvalidContentType")) {
                    Failure::fatal(format!(
                        "the TLS handshake failed ({s}): the server did not answer in TLS: \
                         {PLAIN}"
                    ))
                } else if tls || s.contains("certificate") || s.contains("handshake") {
                    Failure::fatal(format!("the TLS handshake failed: {s}"))
                } else {
                    Failure::fatal(s)
                }
            }
        }
    }

    /// Whether an I/O error on `url` happened in the TLS handshake with a
    /// server that speaks plain HTTP (https:// and its message says so).
    fn tls_phase(&self, url: &str, msg: &str) -> bool {
        url.get(..8).unwrap_or("").eq_ignore_ascii_case("https://")
            && (msg.contains("corrupt message") || msg.contains("InvalidContentType"))
    }
}

/// Read the body of a 200/206 answer to a GET of `span`, checking its
/// length against what was asked and what the server announced.
fn read_body(
    resp: &mut ureq::http::Response<ureq::Body>,
    span: &Span,
) -> std::result::Result<Vec<u8>, Failure> {
    let partial = resp.status().as_u16() == 206;
    let header = |k: &str| {
        resp.headers()
            .get(k)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let announced: Option<u64> = header("content-length").and_then(|v| v.trim().parse().ok());
    let cr = header("content-range");
    let mut body = Vec::with_capacity(announced.unwrap_or(0).min(64 << 20) as usize);
    let res = resp
        .body_mut()
        .with_config()
        .limit(u64::MAX)
        .reader()
        .read_to_end(&mut body);
    if let Err(e) = res {
        return Err(Failure::retry(format!(
            "body truncated or reset after {} bytes{}: {e}",
            body.len(),
            announced.map(|n| format!(" of {n}")).unwrap_or_default()
        )));
    }
    if let Some(n) = announced {
        if body.len() as u64 != n {
            return Err(Failure::retry(format!(
                "body truncated: {} of {n} bytes",
                body.len()
            )));
        }
    }
    let got = body.len() as u64;
    if partial {
        let (a, b, _) = cr
            .as_deref()
            .and_then(content_range)
            .ok_or_else(|| Failure::fatal("206 answer without a valid Content-Range"))?;
        if b - a != got {
            return Err(Failure::retry(format!(
                "body truncated: {got} bytes for Content-Range {a}-{}",
                b - 1
            )));
        }
        let want = match span {
            Span::Range(r) => Some(r.clone()),
            Span::From(o) => Some(*o..b),
            Span::Suffix(_) | Span::All => None,
        };
        if let Some(w) = want {
            if w.start != a || w.end != b {
                return Err(Failure::fatal(format!(
                    "asked for bytes {}-{}, the server sent {a}-{}",
                    w.start,
                    w.end - 1,
                    b - 1
                )));
            }
        }
        Ok(body)
    } else {
        // The whole value (a server that ignores Range); a suffix longer
        // than the value is all of it, as a 206 would have been.
        if let Span::Suffix(n) = span {
            if *n >= got {
                return Ok(body);
            }
        }
        let r = span.within(got).ok_or_else(|| {
            Failure::fatal(format!(
                "bytes {span:?} asked for, but the value holds {got}"
            ))
        })?;
        if r == (0..got) {
            return Ok(body);
        }
        Ok(body[r.start as usize..r.end as usize].to_vec())
    }
}

/// A refusal's reason as the server gives it: a short line of plain text
/// (at most 200 bytes, printable), or nothing.
fn short_reason(resp: &mut ureq::http::Response<ureq::Body>) -> Option<String> {
    let plain = resp
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .is_some_and(|t| t.starts_with("text/plain"));
    if !plain {
        return None;
    }
    let text = resp
        .body_mut()
        .with_config()
        .limit(200)
        .read_to_string()
        .ok()?;
    let text = text.trim();
    (!text.is_empty() && !text.contains('\n') && text.chars().all(|c| !c.is_control()))
        .then(|| text.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write as _;
    use std::net::TcpListener;

    /// A port with nothing listening on it.
    fn dead_port() -> u16 {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    }

    /// The port of a server that accepts and holds every connection and
    /// answers nothing.
    fn silent_server() -> u16 {
        silent_server_counting().0
    }

    /// [`silent_server`], with the number of connections it accepted.
    fn silent_server_counting() -> (u16, Arc<AtomicU64>) {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let n = Arc::new(AtomicU64::new(0));
        let n2 = n.clone();
        std::thread::spawn(move || {
            let mut held = vec![];
            for s in l.incoming().flatten() {
                n2.fetch_add(1, Ordering::SeqCst);
                held.push(s);
            }
        });
        (port, n)
    }

    /// A server that accepts connections and never answers (hung, or
    /// stopped): each request waits for the answer's headers at most
    /// `response_timeout`, and the host soon counts as down. `open` of
    /// such a store waited out 30 s × 5 attempts per document, ten minutes.
    #[test]
    fn a_host_that_never_answers_counts_as_down() {
        let (port, accepted) = silent_server_counting();
        let c = Client::new(HttpConfig {
            retries: 4,
            backoff: Duration::from_millis(10),
            timeout: Duration::from_secs(30),
            response_timeout: Duration::from_millis(200),
            ..HttpConfig::default()
        });
        let t0 = Instant::now();
        let errors: Vec<String> = (0..6)
            .map(|i| {
                c.size(&format!("http://127.0.0.1:{port}/s.zarr/c/{i}"))
                    .unwrap_err()
                    .to_string()
            })
            .collect();
        assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
        // Its wait is long: a request asked and not answered is tried once
        // more, not on the whole schedule (`info` of such a store took 64 s
        // at the default 10 s, now 20 s).
        assert!(
            errors[0].contains("no answer") && errors[0].contains("after 2 attempts"),
            "{}",
            errors[0]
        );
        // A request refused meanwhile says it was not sent, and which one
        // was not answered (a zarr.json the server had answered read as
        // the fault).
        assert!(
            errors[5].contains("not sent: ")
                && errors[5].contains("is not answering")
                && errors[5].contains(&format!(
                    "(last: http://127.0.0.1:{port}/s.zarr/c/0: no answer"
                )),
            "{}",
            errors[5]
        );
        // Two silences, and the host counted as down: nothing more sent.
        assert_eq!(accepted.load(Ordering::SeqCst), 2);
        // After the pause one request tries it again; the others, which
        // would each wait out the same silence, fail meanwhile.
        std::thread::sleep(HOST_PAUSE);
        let c = Arc::new(c);
        let errors: Vec<String> = (0..8)
            .map(|i| {
                let c = c.clone();
                std::thread::spawn(move || {
                    c.size(&format!("http://127.0.0.1:{port}/s.zarr/c/x{i}"))
                        .unwrap_err()
                        .to_string()
                })
            })
            .collect::<Vec<_>>()
            .into_iter()
            .map(|t| t.join().unwrap())
            .collect();
        assert_eq!(accepted.load(Ordering::SeqCst), 3, "{errors:?}");
        assert!(
            errors
                .iter()
                .any(|e| e.contains("one request is trying it again")),
            "{errors:?}"
        );
    }

    /// A proxy whose server behind it died answers 502 to everything: its
    /// host counts as down as one that does not answer at all, where each
    /// file cost its whole schedule of retries (a render through such a
    /// proxy took 105 s to give up).
    #[test]
    fn a_gateway_without_its_server_counts_as_down() {
        let s = Server::start();
        let c = Client::new(quick());
        for i in 0..12 {
            s.fail.lock().unwrap().insert(format!("/s.zarr/c/{i}"), 502);
        }
        let errors: Vec<String> = (0..12)
            .map(|i| {
                c.size(&s.url(&format!("s.zarr/c/{i}")))
                    .unwrap_err()
                    .to_string()
            })
            .collect();
        assert!(
            errors[0].contains("HTTP 502 Bad Gateway") && errors[0].contains("behind a proxy"),
            "{}",
            errors[0]
        );
        let tried: usize = (0..12).map(|i| s.requests(&format!("s.zarr/c/{i}"))).sum();
        assert_eq!(tried, 6, "{errors:?}");
        assert!(errors[11].contains("is not answering"), "{}", errors[11]);
        // A 503 (busy, or down for maintenance) is the server's own answer:
        // retried, and no count toward the host being down.
        let t = Server::start();
        t.fail.lock().unwrap().insert("/s.zarr/c/0".into(), 503);
        let e = c.size(&t.url("s.zarr/c/0")).unwrap_err().to_string();
        assert!(
            e.contains("HTTP 503") && e.contains("after 5 attempts"),
            "{e}"
        );
        assert!(!c
            .hosts
            .lock()
            .unwrap()
            .contains_key(host_of(&t.url("s.zarr/c/0"))));
    }

    /// A server that was there, went away and came back: its requests stop
    /// costing each a whole schedule of retries once the host counts as
    /// down, say why, and it is used again after the pause.
    #[test]
    fn a_host_that_went_away_fails_fast_then_is_tried_again() {
        let port = dead_port();
        let c = Client::new(HttpConfig {
            retries: 4,
            backoff: Duration::from_millis(100),
            connect_timeout: Duration::from_secs(2),
            ..HttpConfig::default()
        });
        let url = |i: usize| format!("http://127.0.0.1:{port}/s.zarr/c/0/0/{i}");
        let t0 = Instant::now();
        let errors: Vec<String> = (0..12)
            .map(|i| c.size(&url(i)).unwrap_err().to_string())
            .collect();
        // Each alone: 5 attempts and 0.1 + 0.2 + 0.4 + 0.8 s of backoff,
        // 18 s for the twelve.
        let took = t0.elapsed();
        assert!(took < Duration::from_secs(6), "{took:?}");
        assert!(errors[0].contains("after 5 attempts"), "{}", errors[0]);
        for e in &errors[2..] {
            assert!(
                e.contains(&format!("127.0.0.1:{port} is not answering"))
                    && e.contains("attempts in a row got no connection or no answer"),
                "{e}"
            );
        }
        // Another host is not affected.
        let other = dead_port();
        let e = c
            .size(&format!("http://127.0.0.1:{other}/x/c/0"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("after 5 attempts"), "{e}");
        // The server comes back (an answer of any status will do): within
        // the pause requests still fail without trying, after it they go
        // through and the host is healthy again.
        let l = TcpListener::bind(("127.0.0.1", port)).unwrap();
        std::thread::spawn(move || {
            for mut s in l.incoming().flatten() {
                let mut buf = [0u8; 4096];
                let _ = std::io::Read::read(&mut s, &mut buf);
                let _ = s.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n");
            }
        });
        let e = c.size(&url(0)).unwrap_err().to_string();
        assert!(e.contains("not answering"), "{e}");
        std::thread::sleep(HOST_PAUSE);
        assert_eq!(c.size(&url(0)).unwrap(), None);
        let hosts = c.hosts.lock().unwrap();
        assert!(!hosts.contains_key(&format!("http://127.0.0.1:{port}")));
        assert_eq!(hosts.len(), 1, "the other host's failures stay counted");
    }

    /// A file a test server holds: its bytes and ETag (`None`: sent
    /// without one).
    type Files = Arc<Mutex<HashMap<String, (Vec<u8>, Option<String>)>>>;

    /// A small file server (one request per connection) with ranges,
    /// `ETag`, `If-Match` (412) and `If-None-Match` (304), answering the
    /// status in `fail` for a path there, and counting requests by path.
    struct Server {
        port: u16,
        files: Files,
        fail: Arc<Mutex<HashMap<String, u16>>>,
        seen: Arc<Mutex<Vec<String>>>,
    }

    impl Server {
        fn start() -> Server {
            let l = TcpListener::bind("127.0.0.1:0").unwrap();
            let port = l.local_addr().unwrap().port();
            let files: Files = Arc::default();
            let fail: Arc<Mutex<HashMap<String, u16>>> = Arc::default();
            let seen: Arc<Mutex<Vec<String>>> = Arc::default();
            let (f2, x2, s2) = (files.clone(), fail.clone(), seen.clone());
            std::thread::spawn(move || {
                for c in l.incoming().flatten() {
                    let (f, x, s) = (f2.clone(), x2.clone(), s2.clone());
                    std::thread::spawn(move || {
                        let _ = serve_one(c, &f, &x, &s);
                    });
                }
            });
            Server {
                port,
                files,
                fail,
                seen,
            }
        }
        fn url(&self, path: &str) -> String {
            format!("http://127.0.0.1:{}/{path}", self.port)
        }
        fn put(&self, path: &str, data: &[u8], etag: Option<&str>) {
            self.files.lock().unwrap().insert(
                format!("/{path}"),
                (data.to_vec(), etag.map(str::to_string)),
            );
        }
        fn requests(&self, path: &str) -> usize {
            let p = format!("/{path}");
            self.seen
                .lock()
                .unwrap()
                .iter()
                .filter(|s| **s == p)
                .count()
        }
    }

    fn serve_one(
        mut c: std::net::TcpStream,
        files: &Files,
        fail: &Mutex<HashMap<String, u16>>,
        seen: &Mutex<Vec<String>>,
    ) -> std::io::Result<()> {
        let mut head = vec![];
        let mut b = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            if c.read(&mut b)? == 0 {
                return Ok(());
            }
            head.push(b[0]);
        }
        let head = String::from_utf8_lossy(&head).to_string();
        let mut lines = head.lines();
        let mut first = lines.next().unwrap_or("").split(' ');
        let method = first.next().unwrap_or("").to_string();
        let path = first.next().unwrap_or("").to_string();
        let hdr = |k: &str| {
            head.lines().skip(1).find_map(|l| {
                let (a, v) = l.split_once(':')?;
                a.trim()
                    .eq_ignore_ascii_case(k)
                    .then(|| v.trim().to_string())
            })
        };
        seen.lock().unwrap().push(path.clone());
        let answer = |c: &mut std::net::TcpStream, status: &str, extra: &str, body: &[u8]| {
            let h = format!(
                "HTTP/1.1 {status}\r\nContent-Length: {}\r\nConnection: close\r\n{extra}\r\n",
                body.len()
            );
            c.write_all(h.as_bytes())?;
            if method != "HEAD" {
                c.write_all(body)?;
            }
            Ok(())
        };
        if let Some(code) = fail.lock().unwrap().get(&path) {
            return answer(&mut c, &format!("{code} Injected"), "", b"");
        }
        let Some((data, etag)) = files.lock().unwrap().get(&path).cloned() else {
            return answer(&mut c, "404 Not Found", "", b"");
        };
        let et = etag
            .as_ref()
            .map(|e| format!("ETag: {e}\r\n"))
            .unwrap_or_default();
        if let (Some(inm), Some(e)) = (hdr("if-none-match"), &etag) {
            if inm == *e {
                return answer(&mut c, "304 Not Modified", &et, b"");
            }
        }
        if let Some(im) = hdr("if-match") {
            if etag.as_deref() != Some(im.as_str()) {
                return answer(&mut c, "412 Precondition Failed", &et, b"");
            }
        }
        let len = data.len();
        match hdr("range").and_then(|r| r.strip_prefix("bytes=").map(str::to_string)) {
            None => answer(&mut c, "200 OK", &et, &data),
            Some(r) => {
                let (x, y) = r.split_once('-').unwrap();
                let (a, e) = if x.is_empty() {
                    (len - y.parse::<usize>().unwrap().min(len), len)
                } else {
                    let a: usize = x.parse().unwrap();
                    let e = if y.is_empty() {
                        len
                    } else {
                        (y.parse::<usize>().unwrap() + 1).min(len)
                    };
                    (a, e)
                };
                let cr = format!("{et}Content-Range: bytes {a}-{}/{len}\r\n", e - 1);
                answer(&mut c, "206 Partial Content", &cr, &data[a..e])
            }
        }
    }

    fn quick() -> HttpConfig {
        HttpConfig {
            retries: 4,
            backoff: Duration::from_millis(50),
            connect_timeout: Duration::from_secs(2),
            ..HttpConfig::default()
        }
    }

    /// A shard replaced on the server (a store converted again under the
    /// same name) while its index is cached: the chunk reads at offsets
    /// from the old index got the new file's bytes (blosc "encoded value
    /// is invalid", or wrong data), in that open and in any later one.
    #[test]
    fn a_replaced_shard_is_not_read_at_the_old_offsets() {
        let s = Server::start();
        let c = Client::new(quick());
        let shard = "s.zarr/0/c/0/0/0";
        let old: Vec<u8> = (0..64u8).collect();
        let new: Vec<u8> = (100..164u8).collect();
        s.put(shard, &old, Some("\"v1\""));
        let (index, len) = c.suffix(&s.url(shard), 16).unwrap().unwrap();
        assert_eq!((&index[..], len), (&old[48..], 64));
        // The same file: read with If-Match, fine.
        let got = c.read_spans(&s.url(shard), &[Span::Range(0..8)]).unwrap();
        assert_eq!(got.unwrap()[0], old[..8]);
        // Replaced: the read at the old offsets fails, saying why.
        s.put(shard, &new, Some("\"v2\""));
        let e = c
            .read_spans(&s.url(shard), &[Span::Range(0..8)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("changed on the server"), "{e}");
        assert!(e.contains(&s.url(shard)), "{e}");
        // A size read of the new version (as the shard reader asks for
        // a length) does not make the old offsets good: the reads keep
        // the ETag of the index they came from, and fail.
        assert_eq!(c.size(&s.url(shard)).unwrap(), Some(64));
        let e = c
            .read_spans(&s.url(shard), &[Span::Range(0..8)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("changed on the server"), "{e}");
        // Its index is read again (not the cached one), and then its
        // chunks are read from the new file.
        let (index, _) = c.suffix(&s.url(shard), 16).unwrap().unwrap();
        assert_eq!(&index[..], &new[48..]);
        let got = c.read_spans(&s.url(shard), &[Span::Range(0..8)]).unwrap();
        assert_eq!(got.unwrap()[0], new[..8]);

        // A server that ignores If-Match but sends the new ETag: the
        // answer of another version is refused too.
        let other = "s.zarr/0/c/1/0/0";
        s.put(other, &old, Some("\"a\""));
        c.suffix(&s.url(other), 16).unwrap();
        s.put(other, &new, Some("\"b\""));
        c.pins
            .lock()
            .unwrap()
            .insert(s.url(other), "W/\"a\"".into());
        let e = c
            .read_spans(&s.url(other), &[Span::Range(0..8)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("changed on the server"), "{e}");

        // Without ETags, as before.
        let plain = "s.zarr/0/c/2/0/0";
        s.put(plain, &old, None);
        c.suffix(&s.url(plain), 16).unwrap();
        let got = c.read_spans(&s.url(plain), &[Span::Range(0..8)]).unwrap();
        assert_eq!(got.unwrap()[0], old[..8]);
    }

    /// A store opened again after it was replaced on the server read the
    /// first open's metadata for the life of the process.
    #[test]
    fn metadata_is_read_again_once_it_may_have_changed() {
        let s = Server::start();
        let c = Client::new(quick());
        for (doc, etag) in [
            ("s.zarr/zarr.json", Some("\"1\"")),
            ("t.zarr/zarr.json", None),
        ] {
            let url = s.url(doc);
            s.put(doc, b"{\"v\": 1}", etag);
            assert_eq!(c.size(&url).unwrap(), Some(8));
            let shard = format!("{}/c/0", &url[..url.len() - 10]);
            s.put(&shard[url.len() - doc.len()..], b"0123456789", etag);
            c.suffix(&shard, 4).unwrap().unwrap();
            // Read again at once: from the cache.
            let n = s.requests(doc);
            assert_eq!(
                c.read_spans(&url, &[Span::All]).unwrap().unwrap()[0],
                b"{\"v\": 1}"
            );
            assert_eq!(s.requests(doc), n);
            // Later: asked for again (304 where there is an ETag).
            std::thread::sleep(META_FRESH + Duration::from_millis(100));
            assert_eq!(
                c.read_spans(&url, &[Span::All]).unwrap().unwrap()[0],
                b"{\"v\": 1}"
            );
            assert_eq!(s.requests(doc), n + 1);
            // Replaced: the new document, and the store's indexes dropped.
            s.put(doc, b"{\"v\": 22}", etag.map(|_| "\"2\""));
            std::thread::sleep(META_FRESH + Duration::from_millis(100));
            assert_eq!(
                c.read_spans(&url, &[Span::All]).unwrap().unwrap()[0],
                b"{\"v\": 22}"
            );
            assert_eq!(c.size(&url).unwrap(), Some(9));
            let hits = c.index_hits.load(Ordering::Relaxed);
            c.suffix(&shard, 4).unwrap().unwrap();
            assert_eq!(
                c.index_hits.load(Ordering::Relaxed),
                hits,
                "{doc}: stale index"
            );
        }
    }

    /// A shard whose reads keep failing: every brick of it repeated the
    /// whole schedule of retries (483 index reads in 180 s of a render).
    /// Now one schedule, then one attempt per read (none while another is
    /// under way); once the file is readable again it is read at once.
    #[test]
    fn a_failing_shard_costs_one_schedule_of_retries() {
        let s = Server::start();
        let c = Arc::new(Client::new(quick()));
        let shard = "s.zarr/0/c/0/0/0";
        s.put(shard, &[7u8; 64], Some("\"x\""));
        s.put("s.zarr/0/c/1/0/0", &[7u8; 64], Some("\"y\""));
        s.fail.lock().unwrap().insert(format!("/{shard}"), 500);
        let url = s.url(shard);
        // Bricks of the shard read at once share one read of its index.
        let t0 = Instant::now();
        let errors: Vec<String> = (0..8)
            .map(|_| {
                let (c, url) = (c.clone(), url.clone());
                std::thread::spawn(move || c.suffix(&url, 16).unwrap_err().to_string())
            })
            .collect::<Vec<_>>()
            .into_iter()
            .map(|t| t.join().unwrap())
            .collect();
        assert_eq!(s.requests(shard), 5, "{errors:?}");
        for e in &errors {
            assert!(
                e.contains("HTTP 500") && e.contains("after 5 attempts"),
                "{e}"
            );
        }
        // Later bricks (the other shard's reads succeed between them):
        // one attempt each, no backoff.
        for _ in 0..20 {
            c.suffix(&s.url("s.zarr/0/c/1/0/0"), 16).unwrap();
            let e = c.suffix(&url, 16).unwrap_err().to_string();
            assert!(e.contains("HTTP 500") && e.contains("tried once"), "{e}");
            assert!(e.contains("after 5 attempts"), "{e}");
        }
        assert_eq!(s.requests(shard), 25);
        assert!(t0.elapsed() < Duration::from_secs(4), "{:?}", t0.elapsed());
        // Another kind of failure: said as it is, not as the earlier one.
        s.fail.lock().unwrap().insert(format!("/{shard}"), 403);
        let e = c.suffix(&url, 16).unwrap_err().to_string();
        assert!(e.contains("HTTP 403") && !e.contains("attempts"), "{e}");
        s.fail.lock().unwrap().insert(format!("/{shard}"), 500);
        let e = c.suffix(&url, 16).unwrap_err().to_string();
        assert!(
            e.contains("HTTP 500") && e.contains("after 5 attempts"),
            "{e}"
        );
        // Readable again: read at once.
        s.fail.lock().unwrap().clear();
        assert_eq!(c.suffix(&url, 16).unwrap().unwrap().1, 64);
        assert!(c.failing.lock().unwrap().is_empty());
    }

    /// A shard that is not there was asked for by every brick of it (995
    /// HEADs and 770 GETs in a render of 30 s): now once in
    /// [`ABSENT_FRESH`], its index and its size alike; put there, it is
    /// read once that has passed.
    #[test]
    fn a_missing_file_is_asked_for_once_a_while() {
        let s = Server::start();
        let c = Client::new(quick());
        let gone = "s.zarr/0/c/0/0/0";
        for _ in 0..20 {
            assert!(c.suffix(&s.url(gone), 16).unwrap().is_none());
            assert!(c.size(&s.url(gone)).unwrap().is_none());
        }
        assert_eq!(s.requests(gone), 1);
        s.put(gone, &[7u8; 64], Some("\"x\""));
        assert!(c.suffix(&s.url(gone), 16).unwrap().is_none());
        for t in c.absent.lock().unwrap().values_mut() {
            *t = t.checked_sub(ABSENT_FRESH).unwrap_or(*t);
        }
        assert_eq!(c.suffix(&s.url(gone), 16).unwrap().unwrap().1, 64);
        assert_eq!(s.requests(gone), 2);
    }

    /// Credentials in a URL were not used and showed in messages; a query
    /// string became part of every key ("not a Zarr store"); port 99999
    /// said "Connection refused"; a token with a line break "failed to
    /// parse header value" without naming the variable.
    #[test]
    fn bad_urls_and_tokens_are_refused_saying_why() {
        let s = Server::start();
        s.put("s.zarr/zarr.json", b"{}", None);
        let c = Client::new(quick());
        let url = format!("http://alice:s3cret@127.0.0.1:{}/s.zarr/zarr.json", s.port);
        let e = c.size(&url).unwrap_err().to_string();
        assert!(!e.contains("s3cret") && !e.contains("alice"), "{e}");
        assert!(
            e.contains("credentials") && e.contains("BRICKYARD_TOKEN"),
            "{e}"
        );
        let url = format!("http://127.0.0.1:{}/s.zarr?token=abc/zarr.json", s.port);
        let e = c.size(&url).unwrap_err().to_string();
        assert!(!e.contains("abc"), "{e}");
        assert!(e.contains("query string") && e.contains("token=…"), "{e}");
        assert!(e.contains("BRICKYARD_TOKEN"), "{e}");
        let e = c
            .size("http://127.0.0.1:99999/s.zarr/zarr.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("invalid port \"99999\""), "{e}");
        assert_eq!(s.requests("s.zarr/zarr.json"), 0);
        assert_eq!(
            redact("https://u:p@h:1/a.zarr?x=1&y#f"),
            "https://h:1/a.zarr?x=…&…"
        );
        assert!(check_url("http://[::1]:8000/a.zarr").is_ok());
        assert!(check_url("http://[::1]:0/a.zarr").is_err());
        assert!(check_url("http://h/a.zarr").is_ok());
        let e = check_url("http:///a.zarr").unwrap_err();
        assert!(e.contains("names no host"), "{e}");
        let e = check_url("http://h/a.zarr#x").unwrap_err();
        assert!(e.contains("a fragment") && !e.contains("token"), "{e}");

        let c = Client::new(HttpConfig {
            token: Some("abc\r\nX-Evil: 1".into()),
            ..quick()
        });
        let e = c.size(&s.url("s.zarr/zarr.json")).unwrap_err().to_string();
        assert!(
            e.contains("BRICKYARD_TOKEN") && e.contains("line break"),
            "{e}"
        );
        assert!(token_problem("abc def\tx").is_none());
    }

    /// `https://` to a plain-HTTP server: 64 s, then "not answering …
    /// timed out (connect)". Now the handshake's failure is named, with
    /// http:// suggested, after one attempt.
    #[cfg(feature = "https")]
    #[test]
    fn https_to_a_plain_http_server_says_so() {
        // A server that waits for a request line that never comes (as
        // a plain-HTTP server does with a TLS greeting).
        let silent = silent_server();
        // One that answers the greeting with an HTTP error.
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let talks = l.local_addr().unwrap().port();
        std::thread::spawn(move || {
            for mut s in l.incoming().flatten() {
                let mut buf = [0u8; 512];
                let _ = s.read(&mut buf);
                let _ = s.write_all(
                    b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
                );
            }
        });
        let c = Client::new(HttpConfig {
            connect_timeout: Duration::from_millis(700),
            ..quick()
        });
        for port in [silent, talks] {
            let t0 = Instant::now();
            let e = c
                .size(&format!("https://127.0.0.1:{port}/s.zarr/c/0"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("TLS") && e.contains("http://"), "{e}");
            assert!(!e.contains("attempts"), "{e}");
            assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
            // The store's other documents fail at once, saying the same.
            let t0 = Instant::now();
            let e = c
                .size(&format!("https://127.0.0.1:{port}/s.zarr/c/1"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("TLS") && e.contains("not tried again"), "{e}");
            assert!(
                t0.elapsed() < Duration::from_millis(200),
                "{:?}",
                t0.elapsed()
            );
        }
    }

    #[test]
    fn content_ranges_parse() {
        assert_eq!(content_range("bytes 0-9/100"), Some((0, 10, Some(100))));
        assert_eq!(content_range("bytes 5-5/*"), Some((5, 6, None)));
        assert_eq!(content_range("bytes 9-5/100"), None);
        assert_eq!(content_range("items 0-9/100"), None);
    }
}
