//! Reads over HTTP(S): ranged GETs with bounded requests in flight,
//! retries with backoff, timeouts, coalescing of nearby ranges and a cache
//! of shard indexes (suffix reads).
//!
//! What is retried: server errors (5xx), 429, timeouts, refused or reset
//! connections and truncated bodies. What is not: 401/403 (access), 404
//! (a missing value reads as absent, which Zarr means as "fill value"),
//! 416 and other client errors. Every error names the URL, the bytes
//! asked for and what happened (`HTTP 403 Forbidden`, `timed out after
//! 30 s`, `body truncated: 100 of 4096 bytes`), and after the last retry
//! says how many attempts were made.

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
    w.get_or_insert_with(|| Arc::new(Client::new(HttpConfig::from_env().unwrap_or_default())))
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
    /// Nobody there: no connection (refused, unreachable, connect timed
    /// out) or no answer to the request sent; counts toward the host
    /// being down.
    unreachable: bool,
    what: String,
}

impl Failure {
    fn retry(what: impl Into<String>) -> Self {
        Failure {
            retry: true,
            unreachable: false,
            what: what.into(),
        }
    }
    fn fatal(what: impl Into<String>) -> Self {
        Failure {
            retry: false,
            unreachable: false,
            what: what.into(),
        }
    }
    fn unreachable(what: impl Into<String>) -> Self {
        Failure {
            retry: true,
            unreachable: true,
            what: what.into(),
        }
    }
}

/// Attempts that found nobody there (no connection, or no answer to a
/// request sent) in a row, over all requests to a host, after which it
/// counts as down.
const HOST_DOWN_AFTER: u32 = 6;
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
    /// exist, read once per process: remote stores are read-only here.
    meta: Mutex<MetaCache>,
    /// Hosts by `scheme://host:port`.
    hosts: Mutex<HashMap<String, HostHealth>>,
}

/// Whole metadata documents by URL (`None`: not there), bounded in bytes.
#[derive(Default)]
struct MetaCache {
    map: HashMap<String, Option<Arc<Vec<u8>>>>,
    bytes: usize,
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
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &HttpConfig {
        &self.cfg
    }

    /// The size of the value at `url` (a HEAD request); `None` on 404.
    pub fn size(&self, url: &str) -> Result<Option<u64>> {
        if is_meta(url) {
            // A metadata document is read whole, once: its length with it.
            return Ok(self.meta_doc(url)?.map(|d| d.len() as u64));
        }
        self.with_retries(url, "HEAD", None, |resp| {
            let len = resp
                .headers()
                .get("content-length")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().parse::<u64>().ok());
            len.ok_or_else(|| Failure::fatal("the answer has no Content-Length"))
        })
    }

    /// The metadata document at `url`, from the cache or one GET.
    fn meta_doc(&self, url: &str) -> Result<Option<Arc<Vec<u8>>>> {
        let hit = self
            .meta
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .map
            .get(url)
            .cloned();
        if let Some(h) = hit {
            self.index_hits.fetch_add(1, Ordering::Relaxed);
            return Ok(h);
        }
        let doc = self.get(url, &Span::All)?.map(Arc::new);
        let size = doc.as_ref().map_or(0, |d| d.len());
        let mut m = self.meta.lock().unwrap_or_else(|e| e.into_inner());
        if size <= META_MAX && m.bytes + size <= META_CACHE_BYTES {
            m.bytes += size;
            m.map.insert(url.to_string(), doc.clone());
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
                            crate::error::StoreError::io(
                                url,
                                std::io::Error::other(format!(
                                    "bytes {s:?} asked for, but the value holds {len}"
                                )),
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
    /// a HEAD request. `None` on 404.
    pub fn suffix(&self, url: &str, n: u64) -> Result<Option<(Arc<Vec<u8>>, u64)>> {
        let key = (url.to_string(), n);
        let hit = self
            .indexes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .map
            .get(&key)
            .cloned();
        if let Some(h) = hit {
            self.index_hits.fetch_add(1, Ordering::Relaxed);
            return Ok(Some(h));
        }
        if n == 0 {
            return Ok(self.size(url)?.map(|len| (Arc::new(vec![]), len)));
        }
        let range = format!("bytes=-{n}");
        let got = self.with_retries(url, "GET", Some(&range), |resp| {
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
            let body = read_body(resp, &Span::Suffix(n))?;
            Ok((body, total))
        });
        // (A value shorter than `n` comes whole, as HTTP says for suffix
        // ranges; an empty one gets 416, an error naming the URL.)
        let Some((body, total)) = got? else {
            return Ok(None);
        };
        self.bytes.fetch_add(body.len() as u64, Ordering::Relaxed);
        let len = match total {
            Some(t) => t,
            // No length in the answer: ask for it.
            None => match self.size(url)? {
                Some(t) => t,
                None => return Ok(None),
            },
        };
        let body = Arc::new(body);
        self.indexes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .put(key, body.clone(), len);
        Ok(Some((body, len)))
    }

    /// GET one span; `None` on 404.
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
        let got = self.with_retries(url, "GET", range.as_deref(), |resp| read_body(resp, span))?;
        if let Some(b) = &got {
            self.bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
        }
        Ok(got)
    }

    /// One request with retries: `Ok(None)` on 404, the value `take` makes
    /// of a 200/206 answer otherwise.
    fn with_retries<T>(
        &self,
        url: &str,
        method: &str,
        range: Option<&str>,
        take: impl Fn(&mut ureq::http::Response<ureq::Body>) -> std::result::Result<T, Failure>,
    ) -> Result<Option<T>> {
        let mut attempt = 0u32;
        loop {
            let res = match self.host_down(url) {
                Some(why) => Err(Failure::fatal(why)),
                None => {
                    let _permit = self.slots.acquire();
                    self.requests.fetch_add(1, Ordering::Relaxed);
                    let r = self.once(url, method, range, &take);
                    self.host_seen(url, r.as_ref().err());
                    r
                }
            };
            match res {
                Ok(v) => return Ok(v),
                Err(f) if f.retry && attempt < self.cfg.retries => {
                    self.retries.fetch_add(1, Ordering::Relaxed);
                    std::thread::sleep(self.backoff(attempt));
                    attempt += 1;
                }
                Err(f) => {
                    self.failures.fetch_add(1, Ordering::Relaxed);
                    let bytes = range.map(|r| format!(" ({r})")).unwrap_or_default();
                    let tries = if attempt > 0 {
                        format!(", after {} attempts", attempt + 1)
                    } else {
                        String::new()
                    };
                    return Err(StoreError::io(
                        url,
                        std::io::Error::other(format!("{method}{bytes}: {}{tries}", f.what)),
                    ));
                }
            }
        }
    }

    /// Why requests to `url`'s host fail without trying, if they do.
    fn host_down(&self, url: &str) -> Option<String> {
        let hosts = self.hosts.lock().unwrap_or_else(|e| e.into_inner());
        let h = hosts.get(host_of(url))?;
        let left = h.down_until?.checked_duration_since(Instant::now())?;
        Some(format!(
            "{} is not answering: {} attempts in a row got no connection or no answer (last: {}); \
             requests to it fail without trying for {:.0} s more",
            host_of(url),
            h.fails_in_a_row,
            h.last,
            left.as_secs_f64().ceil()
        ))
    }

    /// Note how an attempt on `url` ended (`None`: it succeeded).
    fn host_seen(&self, url: &str, failure: Option<&Failure>) {
        let mut hosts = self.hosts.lock().unwrap_or_else(|e| e.into_inner());
        match failure {
            Some(f) if f.unreachable => {
                let h = hosts.entry(host_of(url).to_string()).or_default();
                h.fails_in_a_row += 1;
                h.last = f.what.clone();
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
        take: &impl Fn(&mut ureq::http::Response<ureq::Body>) -> std::result::Result<T, Failure>,
    ) -> std::result::Result<Option<T>, Failure> {
        // An s3:// location is signed for this attempt (the signature
        // holds the time); its token is not a bearer token.
        let s3 = super::s3::is_s3(url);
        let signed;
        let (url, token) = if s3 {
            signed = super::s3::request_url(url, method).map_err(Failure::fatal)?;
            (signed.as_str(), None)
        } else {
            (url, self.cfg.token.as_ref())
        };
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
            if let Some(t) = token {
                rq = rq.header("Authorization", format!("Bearer {t}"));
            }
            rq.call()
        };
        let mut resp = call.map_err(|e| self.classify(e))?;
        let code = resp.status().as_u16();
        match code {
            200 | 206 => take(&mut resp).map(Some),
            404 | 410 => Ok(None),
            401 | 403 => Err(Failure::fatal(format!(
                "HTTP {code} {}: access refused{}",
                status_text(code),
                if s3 {
                    if super::s3::signed() {
                        " (the signed request was refused: check AWS_ACCESS_KEY_ID, \
                         AWS_SECRET_ACCESS_KEY, AWS_SESSION_TOKEN and AWS_REGION; \
                         S3 also answers 403 for a missing key without list permission)"
                    } else {
                        " (an unsigned request: set AWS_ACCESS_KEY_ID and \
                         AWS_SECRET_ACCESS_KEY for a private bucket)"
                    }
                } else if self.cfg.token.is_some() {
                    " (the bearer token was not accepted)"
                } else {
                    " (a token may be needed: set BRICKYARD_TOKEN)"
                }
            ))),
            408 | 429 | 500..=599 => {
                Err(Failure::retry(format!("HTTP {code} {}", status_text(code))))
            }
            _ => Err(Failure::fatal(format!("HTTP {code} {}", status_text(code)))),
        }
    }

    fn classify(&self, e: ureq::Error) -> Failure {
        match e {
            ureq::Error::Timeout(t @ (ureq::Timeout::Connect | ureq::Timeout::Resolve)) => {
                Failure::unreachable(format!(
                    "timed out ({t}) after at most {:.1} s",
                    self.cfg.connect_timeout.as_secs_f64()
                ))
            }
            // Connected, asked, and no answer: as good as nobody there.
            ureq::Error::Timeout(t @ ureq::Timeout::RecvResponse) => Failure::unreachable(format!(
                "no answer ({t}) within {:.1} s",
                self.cfg.response_timeout.as_secs_f64()
            )),
            ureq::Error::Timeout(t) => Failure::retry(format!(
                "timed out ({t}) after at most {:.1} s",
                self.cfg.timeout.as_secs_f64()
            )),
            ureq::Error::HostNotFound => Failure::fatal("host not found"),
            ureq::Error::BadUri(u) => Failure::fatal(format!("not a valid URL: {u}")),
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
            ureq::Error::Io(e) => Failure::retry(format!("connection error: {e}")),
            ureq::Error::BodyStalled => Failure::retry("the body stalled"),
            e @ ureq::Error::Protocol(_) => Failure::retry(format!("protocol error: {e}")),
            e => Failure::fatal(e.to_string()),
        }
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

    /// A server that accepts connections and never answers (hung, or
    /// stopped): each request waits for the answer's headers at most
    /// `response_timeout`, and the host soon counts as down. `open` of
    /// such a store waited out 30 s × 5 attempts per document, ten minutes.
    #[test]
    fn a_host_that_never_answers_counts_as_down() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        // Accept and hold every connection, answer nothing.
        std::thread::spawn(move || {
            let mut held = vec![];
            for s in l.incoming().flatten() {
                held.push(s);
            }
        });
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
        assert!(errors[0].contains("no answer"), "{}", errors[0]);
        assert!(errors[5].contains("is not answering"), "{}", errors[5]);
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

    #[test]
    fn content_ranges_parse() {
        assert_eq!(content_range("bytes 0-9/100"), Some((0, 10, Some(100))));
        assert_eq!(content_range("bytes 5-5/*"), Some((5, 6, None)));
        assert_eq!(content_range("bytes 9-5/100"), None);
        assert_eq!(content_range("items 0-9/100"), None);
    }
}
