//! `brickyard serve STORE…`: store directories read-only over HTTP, so that
//! `info`, `render`, `view` and `convert` elsewhere can read them by URL.
//!
//! Each store is served under `/<its directory name>/`; `/` lists them as
//! JSON. A directory given is a Zarr store (`zarr.json`, `.zgroup` or
//! `.zarray` at its top) or a folder of such stores (served as
//! `/<folder>/<store>/`); a path that does not exist, is not a directory or
//! holds no store is refused at start, naming it. GET and HEAD with a
//! single byte range (`Range: bytes=a-b`, `a-`,
//! `-n`; 416 when unsatisfiable, several ranges answered with the whole
//! file), `Content-Length`, a strong `ETag` (size and modification time)
//! with `If-None-Match` (304), `If-Match` (412) and `If-Range` (the whole
//! file unless it names the current ETag), CORS for loopback origins and
//! those `--allow-origin` names (`*`: any) with the preflight (`OPTIONS`)
//! and `Content-Range`, `Accept-Ranges`, `Content-Length`, `ETag` exposed.
//! Safe by default: loopback unless a bearer token is set (`--token`,
//! `--token-file`; a wrong or missing one gets 401); without a token a
//! request must name a loopback host (`Host`; 421 otherwise), so that a
//! web page whose name is pointed at 127.0.0.1 (DNS rebinding) reads
//! nothing, and pages of other origins cannot read across origins;
//! the access log shows a `token=` parameter as `…`;
//! a path is decoded once, and a segment that is `..`, `.`, empty, hidden
//! (a name starting with `.`, other than Zarr's `.zarray`, `.zgroup`,
//! `.zattrs`, `.zmetadata`), holds a `%` after decoding (double encoding),
//! a backslash or a NUL is refused (403) before the file system is
//! touched; in a served folder only the stores found in it at start are
//! served (a store whose real path is outside the folder is skipped, and
//! the start says so); the file found is then resolved (symlinks
//! followed) and must still lie under its store's root (403 otherwise),
//! and must be a regular file (403 otherwise: a folder or FIFO where a
//! file should be is damage; only a path with nothing there gets 404,
//! which Zarr clients read as an absent chunk; a file that cannot be
//! read gets 403 or 500). Methods that would write
//! get 405; a request with a body (`Content-Length` above 0 or
//! `Transfer-Encoding`) gets 405 (a method that would write) or 413
//! before anything else and its connection is closed without reading the
//! body. The server reads requests itself
//! (tiny_http writes the responses): a head is at most 32 KiB (431), sent
//! within 30 s of its first byte (408); a connection waits 60 s at most
//! for its next request; a response's writes must go out within 30 s
//! each, and at 32 KiB/s on average after 30 s (a response whose client
//! stops reading for 0.2 s gives its worker up meanwhile, so that slow
//! readers do not hold the workers); at most 256 connections
//! are open (64 from one address other than loopback), and beyond that
//! the one that has waited longest for a request is closed to make room.
//! `--workers` requests are answered at once; each request is logged on
//! stderr; Ctrl-C or SIGTERM stops accepting and ends after the requests
//! in progress.
//! `--render` adds remote rendering (`remote`): a WebSocket endpoint and
//! its thin client at `/remote`.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::net::{IpAddr, Shutdown, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, UNIX_EPOCH};
use tiny_http::{HTTPVersion, Header, Method, Response, StatusCode};

/// The thin client of `--render` (the render port written in).
const REMOTE_PAGE: &str = include_str!("remote.html");

#[derive(Args, Clone, Debug)]
pub struct ServeCmd {
    /// Store directories to serve (each under /<directory name>/), or
    /// folders of stores (each store under /<folder>/<store>/).
    #[arg(required = true)]
    pub stores: Vec<PathBuf>,
    /// Address to bind (an IP address, or `localhost`). Anything but
    /// loopback needs a token.
    #[arg(long, default_value = "127.0.0.1", value_parser = parse_bind)]
    pub bind: IpAddr,
    /// Port (0: any free one; the address is printed on the first line).
    #[arg(long, default_value_t = 8000)]
    pub port: u16,
    /// Bearer token every request must carry (`Authorization: Bearer …`).
    #[arg(long, conflicts_with = "token_file")]
    pub token: Option<String>,
    /// File holding the bearer token (first line).
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// A web origin (scheme://host[:port], or `*`) whose pages may read
    /// the stores across origins (CORS), e.g. a viewer hosted elsewhere;
    /// repeat for several. Without it, only pages from this server and
    /// from other loopback servers may; without a token, requests must
    /// also name a loopback host (DNS rebinding).
    #[arg(long = "allow-origin", value_name = "ORIGIN")]
    pub allow_origin: Vec<String>,
    /// Requests answered at once, over all connections (each reads its
    /// file and writes its response on a thread of its own).
    #[arg(long, default_value_t = 16)]
    pub workers: usize,
    /// No access log.
    #[arg(long)]
    pub quiet: bool,
    /// Remote rendering: a WebSocket endpoint streaming frames of views
    /// clients ask for, and the thin client at /remote.
    #[arg(long)]
    pub render: bool,
    /// Port of the render endpoint (0: any free one; printed).
    #[arg(long, default_value_t = 0)]
    pub render_port: u16,
    /// Render sessions at once (more are refused until one ends).
    #[arg(long, default_value_t = 4)]
    pub render_sessions: usize,
    /// Frames sent per second and session, at most.
    #[arg(long, default_value_t = 20.0)]
    pub max_fps: f64,
    /// Brick pool of each render session.
    #[arg(long, default_value = "256MiB")]
    pub render_pool: String,
    /// Host cache of each store, shared by its render sessions.
    #[arg(long, default_value = "1GiB")]
    pub render_host: String,
    /// The web client: its page and WebAssembly bundle at /web/ (open
    /// `/web/#store=../NAME/`), reading the stores in the browser.
    #[arg(long)]
    pub web: bool,
    /// The web client's built bundle (default: BRICKYARD_WEB_DIST, else
    /// `web/` beside the executable's directory, where
    /// `scripts/build-web.sh` puts it).
    #[arg(long, requires = "web")]
    pub web_dist: Option<PathBuf>,
    /// Who renders: auto (a hardware GPU when there is one), gpu or cpu.
    #[arg(long, default_value = "auto")]
    pub backend: String,
}

/// A directory served under `/<name>/`.
struct Mount {
    /// Its canonical path.
    root: PathBuf,
    /// A folder of stores: the stores found in it at start (by name, each
    /// with its canonical root), the only paths served below it. `None`:
    /// the directory is a store itself (or the web client's bundle).
    stores: Option<HashMap<String, PathBuf>>,
}

/// What the server serves and how.
struct Site {
    /// Mount name → what it serves.
    roots: HashMap<String, Mount>,
    /// Lines to print after the first (skipped folder entries, warnings).
    notes: Vec<String>,
    token: Option<String>,
    /// `--allow-origin`: origins besides loopback ones that may read
    /// across origins.
    origins: Vec<String>,
    log: bool,
    /// The render endpoint's port (`--render`), for the /remote page.
    render_port: Option<u16>,
    /// The web client's bundle (`--web`), served at /web/ (it holds no
    /// data: no token needed).
    web: Option<PathBuf>,
}

/// The web client's bundle directory: `--web-dist`, BRICKYARD_WEB_DIST,
/// else `web/` beside the executable's directory; it must hold the page
/// and the WebAssembly module.
fn web_dist(c: &ServeCmd) -> Result<PathBuf> {
    let (dir, how) = match (&c.web_dist, std::env::var_os("BRICKYARD_WEB_DIST")) {
        (Some(d), _) => (d.clone(), "--web-dist"),
        (None, Some(d)) => (PathBuf::from(d), "BRICKYARD_WEB_DIST"),
        (None, None) => {
            let exe = std::env::current_exe().context("--web: cannot find this executable")?;
            let d = exe
                .parent()
                .and_then(|p| p.parent())
                .map(|p| p.join("web"))
                .context("--web: the executable has no parent directory")?;
            (d, "the default location")
        }
    };
    for f in [
        "index.html",
        "app.js",
        "brickyard_web.js",
        "brickyard_web_bg.wasm",
    ] {
        if !dir.join(f).is_file() {
            bail!(
                "--web: {} ({how}) has no {f}: the web client is not built there; run `bash scripts/build-web.sh` (or give --web-dist DIR)",
                dir.display()
            );
        }
    }
    dir.canonicalize()
        .with_context(|| format!("--web: {}: cannot serve it", dir.display()))
}

/// Whether `d` is a Zarr store (a group or an array at its top).
fn is_store(d: &Path) -> bool {
    d.is_dir()
        && ["zarr.json", ".zgroup", ".zarray"]
            .iter()
            .any(|m| d.join(m).is_file())
}

/// The stores directly in the folder `dir` (canonical), by name, sorted,
/// and the stores in it that are not served, each with the reason: a
/// name that cannot be a URL path segment (hidden ones included), or a
/// real path outside the folder (a symlink leading out of it).
fn stores_in(dir: &Path) -> (Vec<(String, PathBuf)>, Vec<String>) {
    let mut stores = vec![];
    let mut skipped = vec![];
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .map(|es| es.filter_map(|e| e.ok()).collect())
        .unwrap_or_default();
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let path = e.path();
        if !is_store(&path) {
            continue;
        }
        let Some(name) = e.file_name().to_str().map(str::to_string) else {
            skipped.push(format!(
                "{}: its name is not UTF-8, so no URL names it",
                path.display()
            ));
            continue;
        };
        if !segment_ok(&name) {
            skipped.push(format!(
                "{}: its name cannot be a URL path segment (hidden, or holding %, \\ or control characters)",
                path.display()
            ));
            continue;
        }
        match path.canonicalize() {
            Ok(real) if real.starts_with(dir) && real != dir => stores.push((name, real)),
            Ok(real) => skipped.push(format!(
                "{}: a link to {}, outside the served folder",
                path.display(),
                real.display()
            )),
            Err(err) => skipped.push(format!("{}: {err}", path.display())),
        }
    }
    (stores, skipped)
}

fn is_loopback(ip: IpAddr) -> bool {
    ip.is_loopback()
}

/// `--bind`: an IP address, or `localhost` (127.0.0.1).
fn parse_bind(s: &str) -> std::result::Result<IpAddr, String> {
    if s.eq_ignore_ascii_case("localhost") {
        return Ok(IpAddr::from([127, 0, 0, 1]));
    }
    s.parse().map_err(|_| {
        format!("expected an IP address (e.g. 127.0.0.1, 0.0.0.0, ::1) or localhost, found {s:?}")
    })
}

/// The bearer token, and a warning when its file is readable by other
/// users of this machine.
fn read_token(c: &ServeCmd) -> Result<(Option<String>, Option<String>)> {
    let mut warning = None;
    let t = match (&c.token, &c.token_file) {
        (Some(t), _) => Some(t.trim().to_string()),
        (None, Some(f)) => {
            let s = std::fs::read_to_string(f)
                .with_context(|| format!("--token-file {}: cannot read it", f.display()))?;
            #[cfg(unix)]
            {
                use std::os::unix::fs::PermissionsExt;
                let mode = std::fs::metadata(f).map_or(0, |m| m.permissions().mode());
                if mode & 0o044 != 0 {
                    warning = Some(format!(
                        "warning: --token-file {}: other users of this machine can read the token \
                         (mode {:o}); make it private with `chmod 600 {}`",
                        f.display(),
                        mode & 0o777,
                        f.display()
                    ));
                }
            }
            Some(s.lines().next().unwrap_or("").trim().to_string())
        }
        (None, None) => None,
    };
    if let Some(t) = &t {
        if t.is_empty() {
            bail!("--token/--token-file: the token is empty");
        }
        if t.chars().any(|c| !c.is_ascii_graphic()) {
            bail!("--token/--token-file: the token must be printable ASCII without spaces");
        }
    }
    Ok((t, warning))
}

fn site(c: &ServeCmd) -> Result<Site> {
    let (token, warning) = read_token(c)?;
    let mut notes: Vec<String> = warning.into_iter().collect();
    if !is_loopback(c.bind) && token.is_none() {
        bail!(
            "--bind {}: serving beyond this machine (a non-loopback address) needs a bearer \
             token: pass --token TOKEN or --token-file FILE (clients send it as \
             `Authorization: Bearer TOKEN`; brickyard reads it from BRICKYARD_TOKEN)",
            c.bind
        );
    }
    // The web client's bundle first: its errors say how to build it.
    let web = if c.web { Some(web_dist(c)?) } else { None };
    let mut roots = HashMap::new();
    for s in &c.stores {
        if !s.exists() {
            bail!(
                "{}: no such folder: expected a store folder (or a folder of stores) to serve",
                s.display()
            );
        }
        let root = s
            .canonicalize()
            .with_context(|| format!("{}: cannot serve it", s.display()))?;
        if !root.is_dir() {
            bail!(
                "{}: not a folder: expected a store folder (or a folder of stores) to serve",
                s.display()
            );
        }
        let name = root
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| segment_ok(n))
            .with_context(|| {
                format!(
                    "{}: its directory name cannot be a URL path (hidden, or holding %, \\ or \
                     control characters)",
                    s.display()
                )
            })?
            .to_string();
        let stores = if is_store(&root) {
            None
        } else {
            let (stores, skipped) = stores_in(&root);
            if stores.is_empty() {
                bail!(
                    "{}: holds no Zarr store: expected a store folder (zarr.json, .zgroup or \
                     .zarray at its top, as `brickyard convert` writes) or a folder with such \
                     stores in it{}",
                    s.display(),
                    skipped
                        .iter()
                        .map(|w| format!("\n  not served: {w}"))
                        .collect::<String>()
                );
            }
            notes.extend(skipped.iter().map(|w| format!("not served: {w}")));
            Some(stores.into_iter().collect())
        };
        let mount = Mount {
            root: root.clone(),
            stores,
        };
        if let Some(prev) = roots.insert(name.clone(), mount) {
            bail!(
                "{} and {} would both be served as /{name}/: serve directories of different names",
                prev.root.display(),
                root.display()
            );
        }
    }
    if let Some(d) = &web {
        if roots.contains_key("web") {
            bail!("--web: a store named `web` would hide the web client at /web/; serve it from a directory of another name");
        }
        roots.insert(
            "web".to_string(),
            Mount {
                root: d.clone(),
                stores: None,
            },
        );
    }
    for o in c.allow_origin.iter().filter(|o| *o != "*") {
        let Some(host) = origin_host(o) else {
            bail!("--allow-origin: expected * or scheme://host[:port] (as a browser sends it), found {o:?}");
        };
        // (A port past 65535 was taken, and named an origin no browser
        // sends. `[::1]` has colons but no port.)
        let port = host.rsplit_once(':').filter(|_| !host.ends_with(']'));
        if let Some((_, p)) = port {
            if p.parse::<u16>().map_or(true, |p| p == 0) {
                bail!("--allow-origin: the port of {o:?} is not 1 to 65535");
            }
        }
    }
    Ok(Site {
        roots,
        notes,
        token,
        origins: c.allow_origin.clone(),
        log: !c.quiet,
        render_port: None,
        web,
    })
}

pub fn run(c: ServeCmd) -> Result<()> {
    let mut site = site(&c)?;
    if c.workers == 0 {
        bail!("--workers: at least 1");
    }
    let mut render = None;
    if !c.render {
        // Render-session flags without the sessions would change nothing.
        // (Told apart from their defaults, as clap declares them above.)
        for (flag, given) in [
            ("render-pool", c.render_pool != "256MiB"),
            ("render-host", c.render_host != "1GiB"),
            ("render-port", c.render_port != 0),
            ("render-sessions", c.render_sessions != 4),
            ("max-fps", c.max_fps != 20.0),
            ("backend", c.backend != "auto"),
        ] {
            if given {
                bail!("--{flag}: applies to render sessions (give --render too)");
            }
        }
    }
    if c.render {
        if !matches!(c.backend.as_str(), "auto" | "gpu" | "cpu") {
            bail!(
                "--backend: expected auto, gpu or cpu, found {:?}",
                c.backend
            );
        }
        for (flag, v) in [
            ("render-pool", &c.render_pool),
            ("render-host", &c.render_host),
        ] {
            if crate::parse_bytes(v).with_context(|| format!("--{flag}"))? == 0 {
                bail!("--{flag}: expected a size above 0 (e.g. 256MiB)");
            }
        }
        if c.render_sessions == 0 {
            bail!("--render-sessions: at least 1");
        }
        if !(c.max_fps > 0.0 && c.max_fps.is_finite()) {
            bail!("--max-fps: a positive rate, got {}", c.max_fps);
        }
        let addr = SocketAddr::new(c.bind, c.render_port);
        let l = std::net::TcpListener::bind(addr)
            .with_context(|| format!("{addr}: cannot listen for render sessions"))?;
        let port = l.local_addr()?.port();
        site.render_port = Some(port);
        let rs = Arc::new(crate::remote::RenderSite {
            roots: served_stores(&site).into_iter().collect(),
            token: site.token.clone(),
            origins: site.origins.clone(),
            backend: c.backend.clone(),
            sessions: c.render_sessions,
            max_fps: c.max_fps,
            pool: crate::parse_bytes(&c.render_pool).context("--render-pool")?,
            host: crate::parse_bytes(&c.render_host).context("--render-host")?,
            log: !c.quiet,
        });
        render = Some((
            format!(
                "render sessions at ws://{}:{port}/render (at most {}, {} fps); the thin client at /remote",
                c.bind, c.render_sessions, c.max_fps
            ),
            l,
            rs,
        ));
    }
    let site = Arc::new(site);
    let addr = SocketAddr::new(c.bind, c.port);
    let listener = TcpListener::bind(addr).with_context(|| format!("{addr}: cannot listen"))?;
    no_delay(&listener);
    let local = listener
        .local_addr()
        .with_context(|| format!("{addr}: cannot listen"))?;
    // Each store by its URL path (a served folder of stores lists those).
    let names: Vec<String> = served_stores(&site).into_iter().map(|(n, _)| n).collect();
    const LISTED: usize = 8;
    // The first line says where (tests and scripts read the port from it).
    eprintln!(
        "serving {} store(s) at http://{local}/ : {}{}{}",
        names.len(),
        names
            .iter()
            .take(LISTED)
            .map(|n| format!("/{n}/"))
            .collect::<Vec<_>>()
            .join(" "),
        match names.len() > LISTED {
            true => format!(" and {} more", names.len() - LISTED),
            false => String::new(),
        },
        if site.token.is_some() {
            " (bearer token required)"
        } else {
            ""
        }
    );
    // (After the address: the first line gives it.)
    for n in &site.notes {
        eprintln!("{n}");
    }
    // A store an interrupted conversion left is served as it is, but not
    // silently: its readers may find levels or chunks missing.
    for (n, root) in served_stores(&site) {
        if let Some(why) = incomplete(&root) {
            eprintln!(
                "warning: /{n}/ ({}) is INCOMPLETE ({why}): the conversion that wrote it did \
                 not finish, so it may lack levels or chunks",
                root.display()
            );
        }
    }
    if let Some(t) = site.token.as_ref().filter(|t| t.len() < 16) {
        eprintln!(
            "note: a token of {} characters is easy to guess; use at least 16 (e.g. `openssl rand -hex 16`)",
            t.len()
        );
    }
    if site.web.is_some() {
        eprintln!(
            "the web client at http://{local}/web/{}",
            names
                .first()
                .map_or(String::new(), |n| format!("#store=../{n}/"))
        );
    }
    if let Some((msg, l, rs)) = render {
        eprintln!("{msg}");
        std::thread::spawn(move || crate::remote::serve(l, rs));
    }
    crate::install_ctrl_c();
    accept_loop(listener, site, c.workers);
    eprintln!("serve: stopped");
    Ok(())
}

/// Why the store at `root` is incomplete, if it is, by the rule `brickyard
/// info` and the readers share.
fn incomplete(root: &Path) -> Option<&'static str> {
    let attrs = brickyard_store::omezarr::read_group_attributes(root)
        .ok()
        .flatten()
        .map(|(_, a)| a);
    let by = attrs
        .as_ref()
        .and_then(|a| a.get(brickyard_store::omezarr::ATTR));
    brickyard_core::pyramid::incomplete_reason(&root.to_string_lossy(), by)
}

/// Every store served, by its URL path (`name`, or `folder/store` in a
/// served folder), with its canonical root; sorted.
fn served_stores(site: &Site) -> Vec<(String, PathBuf)> {
    let mut v: Vec<(String, PathBuf)> = site
        .roots
        .iter()
        .filter(|(n, _)| site.web.is_none() || n.as_str() != "web")
        .flat_map(|(n, m)| match &m.stores {
            None => vec![(n.clone(), m.root.clone())],
            Some(stores) => stores
                .iter()
                .map(|(s, root)| (format!("{n}/{s}"), root.clone()))
                .collect(),
        })
        .collect();
    v.sort();
    v
}

// The connection layer. tiny_http 0.12 reads a request's head without a
// size limit, has no read or write timeouts, starts a thread for every
// connection and drains a request's body (however long) when the request
// is dropped, in the worker that answered it; so `serve` accepts and
// reads requests itself and uses tiny_http only to write responses.

/// Bytes a request's line and headers may take together (431 beyond).
const HEAD_MAX: usize = 32 * 1024;
/// How long an open connection may wait for its next request.
const IDLE: Duration = Duration::from_secs(60);
/// How long a request's head may take once its first byte came (408).
const HEAD_TIME: Duration = Duration::from_secs(30);
/// Each write of a response must go out within this time...
const WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// ...and a request whose writes stall this long gives its worker up.
const STALL: Duration = Duration::from_millis(200);
/// ...and a response must go out at `MIN_RATE` bytes per second on
/// average after this grace (a client that reads too slowly is cut off).
const WRITE_GRACE: Duration = Duration::from_secs(30);
const MIN_RATE: f64 = 32.0 * 1024.0;
/// Connections open at once (more are answered 503 and closed), and from
/// one address other than loopback.
const MAX_CONNECTIONS: usize = 256;
const MAX_PER_PEER: usize = 64;

/// Requests being answered, at most `--workers` at once.
struct Gate {
    busy: Mutex<usize>,
    cv: Condvar,
    max: usize,
}

impl Gate {
    fn enter(&self) -> GateGuard<'_> {
        let mut b = self.busy.lock().unwrap_or_else(|e| e.into_inner());
        while *b >= self.max {
            b = self.cv.wait(b).unwrap_or_else(|e| e.into_inner());
        }
        *b += 1;
        GateGuard(self)
    }

    fn busy(&self) -> usize {
        *self.busy.lock().unwrap_or_else(|e| e.into_inner())
    }
}

struct GateGuard<'a>(&'a Gate);

impl Drop for GateGuard<'_> {
    fn drop(&mut self) {
        *self.0.busy.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
        self.0.cv.notify_one();
    }
}

/// An open connection, as the accept loop sees it.
struct Entry {
    /// To close it when it is evicted.
    stream: TcpStream,
    peer: IpAddr,
    /// Since when it has been waiting for a request (or reading its
    /// head); `None` while a request is answered.
    waiting: Option<Instant>,
    /// Closed to make room: no longer counted.
    evicted: bool,
}

/// The open connections.
#[derive(Default)]
struct Conns {
    next: u64,
    entries: HashMap<u64, Entry>,
}

impl Conns {
    /// Closes the connection that has waited longest for a request among
    /// those `which` selects; false when none waits.
    fn evict(&mut self, which: impl Fn(&Entry) -> bool) -> bool {
        let oldest = self
            .entries
            .values_mut()
            .filter(|e| !e.evicted && e.waiting.is_some() && which(e))
            .min_by_key(|e| e.waiting);
        match oldest {
            Some(e) => {
                e.evicted = true;
                let _ = e.stream.shutdown(Shutdown::Both);
                true
            }
            None => false,
        }
    }
}

/// A connection's place among the open ones, given back on drop.
struct ConnSlot {
    conns: Arc<Mutex<Conns>>,
    id: u64,
}

impl ConnSlot {
    /// A place for a connection from `peer`: when `MAX_CONNECTIONS` are
    /// open (or `MAX_PER_PEER` from that address, loopback aside), the
    /// one that has waited longest for a request is closed to make room
    /// (so connections that send nothing, or a head byte by byte, cannot
    /// shut others out); when all are answering requests, none.
    fn take(conns: &Arc<Mutex<Conns>>, s: &TcpStream) -> std::result::Result<Self, &'static str> {
        let peer = s.peer_addr().map_err(|_| "no peer address")?.ip();
        let stream = s.try_clone().map_err(|_| "out of file descriptors")?;
        let mut c = conns.lock().unwrap_or_else(|e| e.into_inner());
        let live = |c: &Conns, p: Option<IpAddr>| {
            c.entries
                .values()
                .filter(|e| !e.evicted && p.is_none_or(|p| e.peer == p))
                .count()
        };
        if !peer.is_loopback()
            && live(&c, Some(peer)) >= MAX_PER_PEER
            && !c.evict(|e| e.peer == peer)
        {
            return Err("too many connections from this address");
        }
        if live(&c, None) >= MAX_CONNECTIONS && !c.evict(|_| true) {
            return Err("too many connections");
        }
        c.next += 1;
        let id = c.next;
        c.entries.insert(
            id,
            Entry {
                stream,
                peer,
                waiting: Some(Instant::now()),
                evicted: false,
            },
        );
        Ok(ConnSlot {
            conns: conns.clone(),
            id,
        })
    }

    /// Marks the connection as waiting for a request (`true`) or
    /// answering one.
    fn waiting(&self, w: bool) {
        let mut c = self.conns.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(e) = c.entries.get_mut(&self.id) {
            e.waiting = w.then(Instant::now);
        }
    }
}

impl Drop for ConnSlot {
    fn drop(&mut self) {
        let mut c = self.conns.lock().unwrap_or_else(|e| e.into_inner());
        c.entries.remove(&self.id);
    }
}

/// Waits until `l` has a connection to accept or `ms` milliseconds pass.
fn wait_readable(l: &TcpListener, ms: i32) {
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        let mut fd = libc::pollfd {
            fd: l.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one valid pollfd.
        unsafe {
            libc::poll(&mut fd, 1, ms);
        }
    }
    #[cfg(not(unix))]
    {
        let _ = l;
        std::thread::sleep(Duration::from_millis(ms.clamp(1, 10) as u64));
    }
}

/// Accepts connections until Ctrl-C, each read on a thread of its own (at
/// most `MAX_CONNECTIONS`), its requests answered `workers` at a time
/// over all connections; then waits for the requests in progress.
fn accept_loop(listener: TcpListener, site: Arc<Site>, workers: usize) {
    let gate = Arc::new(Gate {
        busy: Mutex::new(0),
        cv: Condvar::new(),
        max: workers,
    });
    let conns = Arc::new(Mutex::new(Conns::default()));
    if let Err(e) = listener.set_nonblocking(true) {
        eprintln!("serve: {e}");
    }
    while !crate::CANCEL.load(Ordering::SeqCst) {
        wait_readable(&listener, 200);
        let (stream, peer) = match listener.accept() {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => continue,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => {
                // (Out of file descriptors, say: wait for some to close.)
                eprintln!("serve: accepting a connection failed: {e}");
                std::thread::sleep(Duration::from_millis(100));
                continue;
            }
        };
        let slot = match ConnSlot::take(&conns, &stream) {
            Ok(s) => s,
            Err(why) => {
                // Answered without waiting: the socket's buffer takes it.
                let _ = stream.set_nonblocking(true);
                let _ = (&stream).write_all(
                    format!(
                        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n\
                         Content-Length: {}\r\nRetry-After: 1\r\nConnection: close\r\n\r\n{why}\n",
                        why.len() + 1
                    )
                    .as_bytes(),
                );
                log_line(
                    &site,
                    &peer.to_string(),
                    "-",
                    "-",
                    503,
                    0,
                    Instant::now(),
                    Some(why),
                );
                continue;
            }
        };
        let (site, gate) = (site.clone(), gate.clone());
        let spawned = std::thread::Builder::new()
            .name("serve-connection".into())
            .spawn(move || connection(&site, &gate, &slot, stream, peer));
        if let Err(e) = spawned {
            eprintln!("serve: cannot start a thread for a connection: {e}");
        }
    }
    drop(listener);
    while gate.busy() > 0 {
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// An accepted connection.
struct Conn {
    stream: TcpStream,
    peer: SocketAddr,
    /// Whether writing a response failed (the connection is then closed).
    broken: std::cell::Cell<bool>,
}

/// A request read from a connection: what `respond` needs of it.
struct Request<'a> {
    method: Method,
    url: String,
    version: HTTPVersion,
    headers: Vec<Header>,
    /// Whether the connection stays open after the response.
    keep_alive: bool,
    conn: &'a Conn,
    /// Its worker slot (`--workers`), held while it is answered.
    permit: Option<GateGuard<'a>>,
}

impl Request<'_> {
    fn method(&self) -> &Method {
        &self.method
    }

    fn url(&self) -> &str {
        &self.url
    }

    fn headers(&self) -> &[Header] {
        &self.headers
    }

    fn remote_addr(&self) -> Option<&SocketAddr> {
        Some(&self.conn.peer)
    }

    /// Sends `r` (its head only for HEAD), paced: a client that reads too
    /// slowly gets an error here and its connection is closed.
    fn respond<R: Read>(mut self, mut r: Response<R>) -> std::io::Result<()> {
        if !self.keep_alive {
            r.add_header(header("Connection", "close"));
        }
        let mut w = std::io::BufWriter::with_capacity(
            64 << 10,
            Paced::new(&self.conn.stream, self.permit.take()),
        );
        let res = r
            .raw_print(
                &mut w,
                self.version.clone(),
                &self.headers,
                self.method == Method::Head,
                None,
            )
            .and_then(|()| w.flush());
        if res.is_err() {
            self.conn.broken.set(true);
        }
        res
    }
}

/// A writer to a connection that fails once the response falls behind
/// `MIN_RATE` (after `WRITE_GRACE`); each write is bounded by the
/// socket's write timeout.
struct Paced<'a> {
    s: &'a TcpStream,
    start: Instant,
    sent: u64,
    /// The worker slot of the request, given up once a write stalls for
    /// `STALL`.
    permit: Option<GateGuard<'a>>,
    /// Whether a write stalled (the socket's timeout is then the rest of
    /// `WRITE_TIMEOUT`).
    patient: bool,
}

impl<'a> Paced<'a> {
    fn new(s: &'a TcpStream, permit: Option<GateGuard<'a>>) -> Self {
        let _ = s.set_write_timeout(Some(STALL));
        Paced {
            s,
            start: Instant::now(),
            sent: 0,
            permit,
            patient: false,
        }
    }
}

impl Write for Paced<'_> {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        let allowed = WRITE_GRACE + Duration::from_secs_f64(self.sent as f64 / MIN_RATE);
        if self.start.elapsed() > allowed {
            return Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "the client reads too slowly",
            ));
        }
        loop {
            match self.s.write(b) {
                Ok(n) => {
                    self.sent += n as u64;
                    return Ok(n);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    if self.patient {
                        return Err(std::io::Error::new(
                            std::io::ErrorKind::TimedOut,
                            "the client read nothing for 30 s",
                        ));
                    }
                    // A slow reader: its worker goes to other requests,
                    // and it gets the rest of the write timeout.
                    self.permit = None;
                    self.patient = true;
                    self.s.set_write_timeout(Some(WRITE_TIMEOUT - STALL))?;
                }
                Err(e) => return Err(e),
            }
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.s.flush()
    }
}

/// Where a request's head ends in `b` (after its blank line), looking
/// from `from` on.
fn head_end(b: &[u8], from: usize) -> Option<usize> {
    (from..b.len()).find_map(|i| match (b[i], b.get(i + 1), b.get(i + 2)) {
        (b'\n', Some(b'\n'), _) => Some(i + 2),
        (b'\n', Some(b'\r'), Some(b'\n')) => Some(i + 3),
        _ => None,
    })
}

/// The next request's head from `s` (bytes read beyond it stay in
/// `buf`): `Ok(None)` when the connection closed or stayed idle, `Err`
/// with a status and reason to answer before closing.
fn read_head(
    mut s: &TcpStream,
    buf: &mut Vec<u8>,
) -> std::result::Result<Option<Vec<u8>>, (u16, &'static str)> {
    let idle_until = Instant::now() + IDLE;
    // Leading empty lines are ignored (RFC 9112, 2.2).
    let blank = buf
        .iter()
        .take_while(|b| matches!(b, b'\r' | b'\n'))
        .count();
    buf.drain(..blank);
    let mut deadline = (!buf.is_empty()).then(|| Instant::now() + HEAD_TIME);
    let mut scanned = 0;
    let mut chunk = [0u8; 4096];
    loop {
        if let Some(end) = head_end(buf, scanned) {
            let rest = buf.split_off(end);
            return Ok(Some(std::mem::replace(buf, rest)));
        }
        scanned = buf.len().saturating_sub(2);
        if buf.len() >= HEAD_MAX {
            return Err((431, "the request's head is too large"));
        }
        let left = deadline
            .unwrap_or(idle_until)
            .saturating_duration_since(Instant::now());
        if left.is_zero() {
            return match deadline {
                Some(_) => Err((408, "the request's head took too long")),
                None => Ok(None),
            };
        }
        let _ = s.set_read_timeout(Some(left));
        let want = (HEAD_MAX - buf.len()).min(chunk.len());
        match s.read(&mut chunk[..want]) {
            Ok(0) => return Ok(None),
            Ok(n) => {
                let mut new = &chunk[..n];
                if buf.is_empty() {
                    let blank = new
                        .iter()
                        .take_while(|b| matches!(b, b'\r' | b'\n'))
                        .count();
                    new = &new[blank..];
                }
                if deadline.is_none() && !new.is_empty() {
                    deadline = Some(Instant::now() + HEAD_TIME);
                }
                buf.extend_from_slice(new);
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::Interrupted
                ) => {}
            Err(_) => return Ok(None),
        }
    }
}

/// A request from its head; `Err` with a status and reason to answer.
fn parse_head<'a>(
    head: &[u8],
    conn: &'a Conn,
) -> std::result::Result<Request<'a>, (u16, &'static str)> {
    let text = std::str::from_utf8(head)
        .ok()
        .filter(|t| t.is_ascii())
        .ok_or((400, "the request's head is not ASCII"))?;
    let mut lines = text.split('\n').map(|l| l.strip_suffix('\r').unwrap_or(l));
    let line = lines.next().unwrap_or("");
    let mut parts = line.split(' ');
    let (Some(m), Some(url), Some(v), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err((400, "malformed request line"));
    };
    let version = match v {
        "HTTP/1.1" => HTTPVersion(1, 1),
        "HTTP/1.0" => HTTPVersion(1, 0),
        v if v.starts_with("HTTP/") => return Err((505, "HTTP/1.0 and HTTP/1.1 only")),
        _ => return Err((400, "malformed request line")),
    };
    let method: Method = m
        .parse()
        .ok()
        .filter(|_| !m.is_empty() && m.bytes().all(|b| b.is_ascii_graphic()))
        .ok_or((400, "malformed request line"))?;
    if url.is_empty() {
        return Err((400, "malformed request line"));
    }
    let mut headers = vec![];
    for l in lines.filter(|l| !l.is_empty()) {
        // (Folded lines are obsolete: RFC 9112, 5.2.)
        if l.starts_with([' ', '\t']) || !l.contains(':') {
            return Err((400, "malformed header"));
        }
        headers.push(
            l.parse::<Header>()
                .map_err(|()| (400, "malformed header"))?,
        );
    }
    // One Host only (RFC 9112, 3.2): which of two a proxy or a cache
    // would take is not known.
    let hosts = headers.iter().filter(|h| h.field.equiv("Host")).count();
    if hosts > 1 {
        return Err((400, "more than one Host header"));
    }
    // (RFC 9112, 3.2: an HTTP/1.1 request without one is answered 400; it
    // was served.)
    if hosts == 0 && version == HTTPVersion(1, 1) {
        return Err((400, "an HTTP/1.1 request must carry a Host header"));
    }
    let connection = headers
        .iter()
        .filter(|h| h.field.equiv("Connection"))
        .map(|h| h.value.as_str().to_ascii_lowercase())
        .collect::<Vec<_>>()
        .join(",");
    let keep_alive =
        version == HTTPVersion(1, 1) && !connection.split(',').any(|t| t.trim() == "close");
    Ok(Request {
        method,
        url: url.to_string(),
        version,
        headers,
        keep_alive,
        conn,
        permit: None,
    })
}

/// Why `rq`, which carries a body, is refused unread: GET and HEAD take
/// none, and nothing here reads one.
fn body_refusal(rq: &Request) -> Option<(u16, &'static str)> {
    let mut body = rq
        .headers()
        .iter()
        .any(|h| h.field.equiv("Transfer-Encoding"));
    for h in rq
        .headers()
        .iter()
        .filter(|h| h.field.equiv("Content-Length"))
    {
        match h.value.as_str().trim().parse::<u64>() {
            Ok(0) => {}
            Ok(_) => body = true,
            Err(_) => return Some((400, "malformed Content-Length")),
        }
    }
    // (A PUT or POST with a body was told 413, as if a smaller body would
    // do: the method is what is refused.)
    match (body, rq.method()) {
        (false, _) => None,
        (true, Method::Get | Method::Head | Method::Options) => Some((
            413,
            "request bodies are refused: this server is read-only (GET and HEAD take none)",
        )),
        (true, _) => Some((405, "read-only: only GET, HEAD and OPTIONS")),
    }
}

/// Answers a request refused before it was read whole (`status`, `why`)
/// and closes the connection: what the client still sends is read for a
/// moment at most (so that the answer is not lost to a reset), never
/// waited for.
fn refuse(site: &Site, conn: &Conn, method: &str, url: &str, status: u16, why: &str, t0: Instant) {
    ALLOW_ORIGIN.with(|o| *o.borrow_mut() = None);
    let mut r = text(status, why).with_header(header("Connection", "close"));
    if status == 405 {
        r = r.with_header(header("Allow", "GET, HEAD, OPTIONS"));
    }
    let mut w = std::io::BufWriter::new(Paced::new(&conn.stream, None));
    let sent = r
        .raw_print(&mut w, HTTPVersion(1, 1), &[], method == "HEAD", None)
        .and_then(|()| w.flush());
    log_line(
        site,
        &conn.peer.to_string(),
        method,
        &redact_token(url),
        status,
        0,
        t0,
        Some(&match sent {
            Ok(()) => why.to_string(),
            Err(e) => format!("{why}; sending failed: {e}"),
        }),
    );
    let _ = conn.stream.shutdown(Shutdown::Write);
    let until = Instant::now() + Duration::from_secs(1);
    let mut left = 256usize << 10;
    let mut b = [0u8; 8192];
    while left > 0 {
        let t = until.saturating_duration_since(Instant::now());
        if t.is_zero() || conn.stream.set_read_timeout(Some(t)).is_err() {
            break;
        }
        match (&conn.stream).read(&mut b) {
            Ok(0) | Err(_) => break,
            Ok(n) => left = left.saturating_sub(n),
        }
    }
}

/// Reads and answers the requests of one connection until it closes, is
/// idle too long, or a request is refused unread.
fn connection(site: &Site, gate: &Gate, slot: &ConnSlot, stream: TcpStream, peer: SocketAddr) {
    let _ = stream.set_nonblocking(false);
    let _ = stream.set_nodelay(true);
    let conn = Conn {
        stream,
        peer,
        broken: std::cell::Cell::new(false),
    };
    let mut buf = Vec::new();
    loop {
        let head = match read_head(&conn.stream, &mut buf) {
            Ok(Some(h)) => h,
            Ok(None) => return,
            Err((status, why)) => {
                return refuse(site, &conn, "-", "-", status, why, Instant::now());
            }
        };
        let t0 = Instant::now();
        let rq = match parse_head(&head, &conn) {
            Ok(rq) => rq,
            Err((status, why)) => return refuse(site, &conn, "-", "-", status, why, t0),
        };
        if let Some((status, why)) = body_refusal(&rq) {
            let (m, u) = (rq.method().to_string(), rq.url().to_string());
            return refuse(site, &conn, &m, &u, status, why, t0);
        }
        let keep_alive = rq.keep_alive;
        slot.waiting(false);
        let mut rq = rq;
        rq.permit = Some(gate.enter());
        answer(site, rq);
        slot.waiting(true);
        if !keep_alive || conn.broken.get() || crate::CANCEL.load(Ordering::SeqCst) {
            return;
        }
    }
}

/// TCP_NODELAY on the listening socket, which the accepted connections
/// inherit (Linux): the server writes a response's head and body
/// separately, and with Nagle's algorithm the body then waits for the
/// client's delayed acknowledgement (about 40 ms per request).
fn no_delay(l: &std::net::TcpListener) {
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        let one: libc::c_int = 1;
        // SAFETY: a valid socket and a c_int option of the right size.
        unsafe {
            libc::setsockopt(
                l.as_raw_fd(),
                libc::IPPROTO_TCP,
                libc::TCP_NODELAY,
                &one as *const libc::c_int as *const libc::c_void,
                std::mem::size_of::<libc::c_int>() as libc::socklen_t,
            );
        }
    }
    #[cfg(not(unix))]
    let _ = l;
}

fn header(k: &str, v: &str) -> Header {
    Header::from_bytes(k.as_bytes(), v.as_bytes()).expect("valid header")
}

thread_local! {
    /// The `Access-Control-Allow-Origin` of the request this worker is
    /// answering (`None`: the requesting origin may not read across
    /// origins).
    static ALLOW_ORIGIN: std::cell::RefCell<Option<String>> = const { std::cell::RefCell::new(None) };
}

/// Whether `host` (a `Host` header's or an origin's host, with or without
/// a port) names this machine's loopback: `localhost` (or a name under
/// it), 127.0.0.0/8, `[::1]`.
pub(crate) fn loopback_host(host: &str) -> bool {
    let h = host.trim();
    let name = if let Some(r) = h.strip_prefix('[') {
        r.split(']').next().unwrap_or("")
    } else {
        match h.rsplit_once(':') {
            Some((n, port)) if port.bytes().all(|b| b.is_ascii_digit()) => n,
            _ => h,
        }
    };
    let name = name.trim_end_matches('.').to_ascii_lowercase();
    name == "localhost"
        || name.ends_with(".localhost")
        || name.parse::<IpAddr>().is_ok_and(|a| a.is_loopback())
}

/// The host part of an origin `scheme://host[:port]`; `None` when it is
/// not one.
pub(crate) fn origin_host(origin: &str) -> Option<&str> {
    let (scheme, rest) = origin.split_once("://")?;
    (!scheme.is_empty()
        && scheme
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"+-.".contains(&b))
        && !rest.is_empty()
        && !rest.contains(['/', '?', '#', '@']))
    .then_some(rest)
}

/// Whether a page of `origin` may use this server across origins: a
/// loopback origin, or one `--allow-origin` names (`*`: any).
pub(crate) fn origin_allowed(origin: &str, allowed: &[String]) -> bool {
    origin_host(origin).is_some_and(loopback_host)
        || allowed
            .iter()
            .any(|a| a == "*" || a.eq_ignore_ascii_case(origin))
}

fn cors(h: &mut Vec<Header>) {
    let Some(origin) = ALLOW_ORIGIN.with(|o| o.borrow().clone()) else {
        return;
    };
    if origin != "*" {
        h.push(header("Vary", "Origin"));
    }
    h.push(header("Access-Control-Allow-Origin", &origin));
    h.push(header(
        "Access-Control-Expose-Headers",
        "Content-Range, Accept-Ranges, Content-Length, ETag",
    ));
}

/// Percent-decode once; `None` for a malformed escape or non-UTF-8.
fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// Zarr's own metadata names: the only hidden names served.
const ZARR_DOTFILES: [&str; 4] = [".zarray", ".zgroup", ".zattrs", ".zmetadata"];

/// A decoded path segment that may be looked up: not empty, `.` or `..`,
/// not hidden (a name starting with `.`, other than Zarr's metadata:
/// `.git`, `.aws`, `.env` … are never served), without `%` (double
/// encoding), `\`, `/`, NUL or control characters.
fn segment_ok(s: &str) -> bool {
    !(s.is_empty()
        || (s.starts_with('.') && !ZARR_DOTFILES.contains(&s))
        || s.contains(['%', '\\', '\0', '/'])
        || s.chars().any(char::is_control))
}

/// The outcome of resolving a request path.
enum Target {
    Index,
    File(PathBuf),
    /// Status and reason.
    Refused(u16, &'static str),
}

fn resolve(site: &Site, url: &str) -> Target {
    let path = url.split(['?', '#']).next().unwrap_or("");
    let Some(rest) = path.strip_prefix('/') else {
        return Target::Refused(400, "the path must start with /");
    };
    if rest.is_empty() {
        return Target::Index;
    }
    // A folder's path: nothing is listed (Zarr readers never ask for one).
    if rest.ends_with('/') {
        return Target::Refused(404, "a folder: nothing is listed here, ask for a file");
    }
    let mut segs = vec![];
    for raw in rest.split('/') {
        let Some(s) = percent_decode(raw) else {
            return Target::Refused(400, "malformed percent-encoding");
        };
        if !segment_ok(&s) {
            return Target::Refused(403, "path segment refused");
        }
        segs.push(s);
    }
    let Some(mount) = site.roots.get(&segs[0]) else {
        return Target::Refused(404, "no such store");
    };
    // In a served folder, only the stores found in it at start, each
    // within its own root.
    let (root, rest) = match &mount.stores {
        None => (&mount.root, &segs[1..]),
        Some(stores) => match segs.get(1).and_then(|s| stores.get(s)) {
            Some(root) => (root, &segs[2..]),
            None if segs.len() == 1 => return Target::Refused(404, "not a file"),
            None => return Target::Refused(404, "no such store"),
        },
    };
    let mut p = root.clone();
    for s in rest {
        p.push(s);
    }
    // Follow symlinks; the result must still be inside the root.
    match p.canonicalize() {
        Ok(real) if !real.starts_with(root) => Target::Refused(403, "outside the served store"),
        // (A link inside the store to a hidden file in it.)
        Ok(real)
            if !real
                .strip_prefix(root)
                .unwrap_or(&real)
                .iter()
                .all(|c| c.to_str().is_some_and(segment_ok)) =>
        {
            Target::Refused(403, "path segment refused")
        }
        Ok(real) if real.is_file() => Target::File(real),
        // A folder or a FIFO where a client asks for a file is damage, not
        // an absent key: Zarr clients read a 404 as the fill value.
        Ok(_) => Target::Refused(403, "not a regular file"),
        Err(e) => {
            let (code, why) = unreadable(&e);
            Target::Refused(code, why)
        }
    }
}

/// The answer for a file the server cannot read: 404 only where nothing is
/// there (Zarr clients take a 404 for an absent chunk and read the fill
/// value), 403 where it may not be read, 500 otherwise.
fn unreadable(e: &std::io::Error) -> (u16, &'static str) {
    match e.kind() {
        std::io::ErrorKind::NotFound | std::io::ErrorKind::NotADirectory => (404, "not found"),
        std::io::ErrorKind::PermissionDenied => (403, "cannot be read"),
        _ => (500, "cannot be read"),
    }
}

/// A single range of `Range: bytes=…` over `len` bytes: `Ok(None)` to
/// send the whole file (no, malformed or several ranges), `Err(())` when
/// unsatisfiable.
#[allow(clippy::result_unit_err)]
pub fn parse_range(v: &str, len: u64) -> std::result::Result<Option<(u64, u64)>, ()> {
    let Some(spec) = v.trim().strip_prefix("bytes=") else {
        return Ok(None);
    };
    if spec.contains(',') {
        return Ok(None);
    }
    let Some((a, b)) = spec.trim().split_once('-') else {
        return Ok(None);
    };
    let (a, b) = (a.trim(), b.trim());
    // Digits only (`+1` or ` 1` is no byte position: RFC 9110, 14.1.1).
    let num = |s: &str| {
        (!s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse::<u64>().ok())
            .flatten()
    };
    let (start, end) = match (a.is_empty(), b.is_empty()) {
        (true, true) => return Ok(None),
        (true, false) => {
            let Some(n) = num(b) else { return Ok(None) };
            if n == 0 || len == 0 {
                return Err(());
            }
            (len - n.min(len), len)
        }
        (false, _) => {
            let Some(s) = num(a) else { return Ok(None) };
            let e = if b.is_empty() {
                len
            } else {
                match num(b) {
                    Some(e) if e >= s => e.saturating_add(1).min(len),
                    _ => return Ok(None),
                }
            };
            if s >= len {
                return Err(());
            }
            (s, e)
        }
    };
    Ok(Some((start, end)))
}

fn etag_of(m: &std::fs::Metadata) -> String {
    let t = m
        .modified()
        .ok()
        .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    format!("\"{:x}-{:x}\"", m.len(), t)
}

/// `url` with the value of a `token=` query parameter replaced by `…`
/// (the thin client's page takes its token so), and control characters
/// escaped: what the access log may show.
pub(crate) fn redact_token(url: &str) -> String {
    let shown = match url.split_once('?') {
        Some((path, query)) => {
            let q: Vec<String> = query
                .split('&')
                .map(|kv| match kv.split_once('=') {
                    Some(("token", _)) => "token=…".to_string(),
                    _ => kv.to_string(),
                })
                .collect();
            format!("{path}?{}", q.join("&"))
        }
        None => url.to_string(),
    };
    loggable(&shown)
}

/// `s` with control characters escaped, so that what a client sends
/// cannot start a line of its own in the log.
pub(crate) fn loggable(s: &str) -> String {
    s.chars()
        .flat_map(|c| {
            if c.is_control() {
                c.escape_default().collect::<Vec<char>>()
            } else {
                vec![c]
            }
        })
        .collect()
}

fn token_ok(site: &Site, rq: &Request) -> bool {
    let Some(want) = &site.token else {
        return true;
    };
    let got = rq
        .headers()
        .iter()
        .find(|h| h.field.equiv("Authorization"))
        .map(|h| h.value.as_str().trim())
        // The scheme's name is case-insensitive (RFC 9110, 11.1).
        .and_then(|v| v.split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, t)| t.trim())
        .unwrap_or("");
    // Compare in constant time for equal lengths.
    got.len() == want.len()
        && got
            .bytes()
            .zip(want.bytes())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
}

fn req_header<'a>(rq: &'a Request, k: &'static str) -> Option<&'a str> {
    rq.headers()
        .iter()
        .find(|h| h.field.equiv(k))
        .map(|h| h.value.as_str())
}

fn answer(site: &Site, rq: Request) {
    let t0 = Instant::now();
    let method = rq.method().clone();
    let url = redact_token(rq.url());
    // Who may read this answer across origins: with `--allow-origin *`
    // anyone; else the requesting page's origin when it is allowed (a
    // page of this server sends none for its own reads).
    let allow = if site.origins.iter().any(|o| o == "*") {
        Some("*".to_string())
    } else {
        req_header(&rq, "Origin")
            .filter(|o| origin_allowed(o, &site.origins))
            .map(str::to_string)
    };
    ALLOW_ORIGIN.with(|o| *o.borrow_mut() = allow);
    let peer = rq
        .remote_addr()
        .map(|a| a.to_string())
        .unwrap_or_else(|| "-".into());
    let (status, bytes, res) = respond(site, rq);
    log_line(
        site,
        &peer,
        &method.to_string(),
        &url,
        status,
        bytes,
        t0,
        res.as_deref(),
    );
}

/// A line of the access log (`url` already redacted).
#[allow(clippy::too_many_arguments)]
fn log_line(
    site: &Site,
    peer: &str,
    method: &str,
    url: &str,
    status: u16,
    bytes: u64,
    t0: Instant,
    note: Option<&str>,
) {
    if site.log {
        let now = std::time::SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default()
            .as_secs_f64();
        eprintln!(
            "{now:.3} {peer} {method} {url} {status} {bytes} {:.1}ms{}",
            t0.elapsed().as_secs_f64() * 1e3,
            note.map(|e| format!(" ({e})")).unwrap_or_default()
        );
    }
}

fn empty(status: u16, mut h: Vec<Header>) -> Response<std::io::Empty> {
    cors(&mut h);
    let mut r = Response::new(StatusCode(status), h, std::io::empty(), Some(0), None);
    r.add_header(header("Cache-Control", "no-cache"));
    r
}

fn text(status: u16, msg: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    let mut h = vec![header("Content-Type", "text/plain; charset=utf-8")];
    cors(&mut h);
    let body = format!("{msg}\n").into_bytes();
    let n = body.len();
    Response::new(
        StatusCode(status),
        h,
        std::io::Cursor::new(body),
        Some(n),
        None,
    )
}

/// Answer `rq`: `(status, body bytes, note for the log)`.
fn respond(site: &Site, rq: Request) -> (u16, u64, Option<String>) {
    let send_err = |e: std::io::Error| Some(format!("sending failed: {e}"));
    match rq.method() {
        Method::Get | Method::Head => {}
        Method::Options => {
            let h = vec![
                header("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS"),
                header(
                    "Access-Control-Allow-Headers",
                    "Range, Authorization, If-None-Match, If-Match, If-Range, Content-Type",
                ),
                header("Access-Control-Max-Age", "86400"),
                header("Allow", "GET, HEAD, OPTIONS"),
            ];
            let r = rq.respond(empty(204, h)).err().and_then(send_err);
            return (204, 0, r);
        }
        _ => {
            let r = text(405, "read-only: only GET, HEAD and OPTIONS")
                .with_header(header("Allow", "GET, HEAD, OPTIONS"));
            let e = rq.respond(r).err().and_then(send_err);
            return (405, 0, e);
        }
    }
    // Without a token the server answers only requests that name it by a
    // loopback host: a page whose name an attacker points at 127.0.0.1
    // (DNS rebinding) is refused. (HTTP/1.0 requests may omit Host; HTTP/1.1
    // ones were refused without one in `parse_head`.)
    if site.token.is_none() {
        if let Some(h) = req_header(&rq, "Host").filter(|h| !loopback_host(h)) {
            let why =
                format!("host {h:?} is not this machine's loopback (a token lets other names in)");
            let e = rq
                .respond(text(421, "this server answers loopback host names only"))
                .err()
                .and_then(send_err);
            return (421, 0, e.or(Some(why)));
        }
    }
    // The thin client's page holds no data: it asks for the token itself.
    if let (Some(port), "/remote") = (site.render_port, rq.url().split('?').next().unwrap_or("")) {
        let body = REMOTE_PAGE
            .replace("__RENDER_PORT__", &port.to_string())
            .into_bytes();
        let n = body.len();
        let h = vec![
            header("Content-Type", "text/html; charset=utf-8"),
            header("Cache-Control", "no-cache"),
        ];
        let r = Response::new(
            StatusCode(200),
            h,
            std::io::Cursor::new(body),
            Some(n),
            None,
        );
        let e = rq.respond(r).err().and_then(send_err);
        return (200, n as u64, e);
    }
    // The web client's page and bundle hold no data either.
    let path = rq.url().split(['?', '#']).next().unwrap_or("").to_string();
    let web_page = site.web.is_some() && (path == "/web" || path.starts_with("/web/"));
    if web_page && path == "/web" {
        let r = empty(301, vec![header("Location", "/web/")]);
        let e = rq.respond(r).err().and_then(send_err);
        return (301, 0, e);
    }
    if !web_page && !token_ok(site, &rq) {
        let r = text(401, "a valid bearer token is needed")
            .with_header(header("WWW-Authenticate", "Bearer"));
        let e = rq.respond(r).err().and_then(send_err);
        return (401, 0, e);
    }
    let url = if web_page && path.ends_with('/') {
        format!("{path}index.html")
    } else {
        rq.url().to_string()
    };
    let file = match resolve(site, &url) {
        Target::Index => {
            // Every store by its path (`folder/store` in a served folder,
            // as the render endpoint names them): the folder's name alone
            // named no store (`/remote` offered it and could open none).
            let names: Vec<String> = served_stores(site).into_iter().map(|(n, _)| n).collect();
            let body = serde_json::json!({ "stores": names })
                .to_string()
                .into_bytes();
            let n = body.len();
            let mut h = vec![header("Content-Type", "application/json")];
            cors(&mut h);
            let r = Response::new(
                StatusCode(200),
                h,
                std::io::Cursor::new(body),
                Some(n),
                None,
            );
            let e = rq.respond(r).err().and_then(send_err);
            return (200, n as u64, e);
        }
        Target::Refused(code, why) => {
            let e = rq.respond(text(code, why)).err().and_then(send_err);
            return (code, 0, e.or(Some(why.to_string())));
        }
        Target::File(p) => p,
    };
    let opened = File::open(&file).and_then(|f| {
        let m = f.metadata()?;
        Ok((f, m))
    });
    let (mut f, meta) = match opened {
        Ok(x) => x,
        Err(e) => {
            let (code, why) = unreadable(&e);
            let r = rq.respond(text(code, why)).err().and_then(send_err);
            return (code, 0, r.or(Some(format!("{}: {e}", file.display()))));
        }
    };
    let len = meta.len();
    let etag = etag_of(&meta);
    let mut h = vec![
        header("Accept-Ranges", "bytes"),
        header("ETag", &etag),
        header("Cache-Control", "no-cache"),
    ];
    if let Some(inm) = req_header(&rq, "If-None-Match") {
        if inm.split(',').any(|t| {
            let t = t.trim();
            t == "*" || t.trim_start_matches("W/") == etag
        }) {
            let e = rq.respond(empty(304, h)).err().and_then(send_err);
            return (304, 0, e);
        }
    }
    let ext = file.extension().and_then(|e| e.to_str()).unwrap_or("");
    let ctype = if web_page && ext == "html" {
        "text/html; charset=utf-8"
    } else if web_page && ext == "js" {
        "text/javascript"
    } else if web_page && ext == "wasm" {
        "application/wasm"
    } else if ext == "json"
        || file
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| ZARR_DOTFILES.contains(&n))
    {
        "application/json"
    } else {
        "application/octet-stream"
    };
    h.push(header("Content-Type", ctype));
    cors(&mut h);
    // A write-back client's precondition: the file must still be the one
    // it knows (RFC 9110, 13.1.1; strong comparison).
    let tag_matches = |v: &str| v.split(',').any(|t| t.trim() == "*" || t.trim() == etag);
    if let Some(im) = req_header(&rq, "If-Match") {
        if !tag_matches(im) {
            let e = rq.respond(empty(412, h)).err().and_then(send_err);
            return (412, 0, e);
        }
    }
    // A range resumed from an older copy: the whole file instead, unless
    // the validator is this file's ETag (dates are not strong validators
    // here, so they never match).
    let range_ok = req_header(&rq, "If-Range").is_none_or(|v| v.trim() == etag);
    let range = match req_header(&rq, "Range").filter(|_| range_ok) {
        None => Ok(None),
        Some(v) => parse_range(v, len),
    };
    let (status, start, end) = match range {
        Ok(None) => (200, 0, len),
        Ok(Some((a, b))) => {
            h.push(header(
                "Content-Range",
                &format!("bytes {a}-{}/{len}", b - 1),
            ));
            (206, a, b)
        }
        Err(()) => {
            h.push(header("Content-Range", &format!("bytes */{len}")));
            let r = Response::new(StatusCode(416), h, std::io::empty(), Some(0), None);
            let e = rq.respond(r).err().and_then(send_err);
            return (416, 0, e);
        }
    };
    if let Err(e) = f.seek(SeekFrom::Start(start)) {
        let r = rq.respond(text(500, "read error")).err().and_then(send_err);
        return (500, 0, r.or(Some(e.to_string())));
    }
    let n = end - start;
    let body = f.take(n);
    let head = *rq.method() == Method::Head;
    // Always Content-Length, never chunked (tiny_http chunks from 32 KiB).
    let r = Response::new(StatusCode(status), h, body, Some(n as usize), None)
        .with_chunked_threshold(usize::MAX);
    let e = rq.respond(r).err().and_then(send_err);
    (status, if head { 0 } else { n }, e)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_names_origins_and_what_the_log_shows() {
        for h in [
            "localhost",
            "localhost:8000",
            "127.0.0.1",
            "127.1.2.3:9",
            "[::1]:80",
            "a.localhost",
            "LocalHost.",
        ] {
            assert!(loopback_host(h), "{h}");
        }
        for h in [
            "attacker.example",
            "10.0.0.1:80",
            "localhost.attacker.example",
            "[::2]",
            "127.0.0.1.nip.io",
        ] {
            assert!(!loopback_host(h), "{h}");
        }
        assert!(origin_allowed("http://localhost:5173", &[]));
        assert!(!origin_allowed("http://example.org", &[]));
        assert!(!origin_allowed("null", &[]));
        assert!(origin_allowed(
            "https://example.org",
            &["https://example.org".into()]
        ));
        assert!(origin_allowed("https://x.org", &["*".into()]));
        assert_eq!(
            redact_token("/remote?store=a&token=s3cret&x=1"),
            "/remote?store=a&token=…&x=1"
        );
        assert_eq!(loggable("a\nFAKE"), "a\\nFAKE");
    }

    #[test]
    fn ranges() {
        assert_eq!(parse_range("bytes=0-9", 100), Ok(Some((0, 10))));
        assert_eq!(parse_range("bytes=90-", 100), Ok(Some((90, 100))));
        assert_eq!(parse_range("bytes=-10", 100), Ok(Some((90, 100))));
        assert_eq!(parse_range("bytes=-200", 100), Ok(Some((0, 100))));
        assert_eq!(parse_range("bytes=95-200", 100), Ok(Some((95, 100))));
        assert_eq!(parse_range("bytes=100-", 100), Err(()));
        assert_eq!(parse_range("bytes=-0", 100), Err(()));
        assert_eq!(parse_range("bytes=0-1,5-6", 100), Ok(None));
        assert_eq!(parse_range("bytes=5-1", 100), Ok(None));
        assert_eq!(parse_range("items=0-1", 100), Ok(None));
        // Byte positions are digits only.
        assert_eq!(parse_range("bytes=+1-5", 100), Ok(None));
        assert_eq!(parse_range("bytes=1-+5", 100), Ok(None));
        assert_eq!(parse_range("bytes=-+5", 100), Ok(None));
    }

    #[test]
    fn request_heads_end_at_a_blank_line() {
        assert_eq!(head_end(b"GET / HTTP/1.1\r\nA: b\r\n\r\nnext", 0), Some(24));
        assert_eq!(head_end(b"GET / HTTP/1.1\nA: b\n\n", 0), Some(21));
        assert_eq!(head_end(b"GET / HTTP/1.1\r\nA: b\r\n", 0), None);
    }

    #[test]
    fn segments() {
        for bad in ["..", ".", "", "%2e%2e", "a\\b", "a%00"] {
            assert!(!segment_ok(bad), "{bad}");
        }
        assert!(segment_ok("zarr.json") && segment_ok(".zarray") && segment_ok("c"));
        for hidden in [".aws", ".git", ".env", ".zarray.bak", "..."] {
            assert!(!segment_ok(hidden), "{hidden}");
        }
        assert!(segment_ok(".zmetadata") && segment_ok("a.b") && segment_ok("x."));
        assert_eq!(percent_decode("%2e%2E").as_deref(), Some(".."));
        assert_eq!(percent_decode("%252e").as_deref(), Some("%2e"));
        assert_eq!(percent_decode("%2"), None);
    }
}
