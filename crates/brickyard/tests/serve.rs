//! `brickyard serve` and remote stores end to end: what is read over HTTP
//! equals what is read from disk (info, a rendered image, a converted
//! copy); the server answers ranges, ETags and CORS as HTTP says, and
//! refuses traversal, writes, bad tokens and unprotected public binds.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "failed: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A 128³ u8 Mandelbulb in 32³ bricks and 64³ shards.
fn store(dir: &Path) -> PathBuf {
    let store = dir.join("m.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "128",
        "--dtype",
        "u8",
        "--quiet",
        "--brick",
        "32",
        "--shard",
        "64",
    ]));
    store
}

/// A running `brickyard serve`; killed on drop.
struct Served {
    child: Child,
    port: u16,
    log: Arc<Mutex<String>>,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn serve(stores: &[&Path], extra: &[&str]) -> Served {
    let mut cmd = bin();
    cmd.arg("serve")
        .args(stores)
        .args(["--port", "0"])
        .args(extra);
    let mut child = cmd.stderr(Stdio::piped()).spawn().unwrap();
    let mut err = BufReader::new(child.stderr.take().unwrap());
    let mut first = String::new();
    err.read_line(&mut first).unwrap();
    let port: u16 = first
        .split("127.0.0.1:")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no address in {first:?}"));
    let log = Arc::new(Mutex::new(first));
    let l2 = log.clone();
    std::thread::spawn(move || {
        let mut line = String::new();
        while err.read_line(&mut line).unwrap_or(0) > 0 {
            l2.lock().unwrap().push_str(&line);
            line.clear();
        }
    });
    Served { child, port, log }
}

/// One raw HTTP/1.1 request (paths sent exactly as given): status,
/// headers (lower-case names) and body.
fn http(
    port: u16,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
) -> (u16, Vec<(String, String)>, Vec<u8>) {
    let mut c = TcpStream::connect(("127.0.0.1", port)).unwrap();
    // (Host: localhost unless the headers name another.)
    let host = if headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("host")) {
        ""
    } else {
        "Host: localhost\r\n"
    };
    let mut rq = format!("{method} {path} HTTP/1.1\r\n{host}Connection: close\r\n");
    for (k, v) in headers {
        rq.push_str(&format!("{k}: {v}\r\n"));
    }
    rq.push_str("\r\n");
    c.write_all(rq.as_bytes()).unwrap();
    let mut all = vec![];
    c.read_to_end(&mut all).unwrap();
    let split = all
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a complete head");
    let head = String::from_utf8_lossy(&all[..split]).into_owned();
    let body = all[split + 4..].to_vec();
    let mut lines = head.lines();
    let status: u16 = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let hs = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    (status, hs, body)
}

fn get<'a>(h: &'a [(String, String)], k: &str) -> Option<&'a str> {
    h.iter().find(|(n, _)| n == k).map(|(_, v)| v.as_str())
}

fn png_rgba(p: &Path) -> Vec<u8> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let n = r.next_frame(&mut buf).unwrap().buffer_size();
    buf.truncate(n);
    buf
}

/// `info --json` without what only a local store has (its path and sizes).
fn info_json(store: &str, env: &[(&str, &str)]) -> serde_json::Value {
    let mut c = bin();
    c.args(["info", store, "--json"]);
    for (k, v) in env {
        c.env(k, v);
    }
    info_json_of(c)
}

/// The `info --json` that `c` prints, without what differs between copies
/// of a store (its path, its size on disk).
fn info_json_of(mut c: Command) -> serde_json::Value {
    let mut v: serde_json::Value = serde_json::from_str(&ok(&c.output().unwrap())).unwrap();
    v["path"] = serde_json::Value::Null;
    for l in v["levels"].as_array_mut().unwrap() {
        l["bytes_on_disk"] = serde_json::Value::Null;
    }
    v
}

#[test]
fn remote_reads_equal_local_reads() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let sv = serve(&[&st], &[]);
    let url = format!("http://127.0.0.1:{}/m.ome.zarr", sv.port);

    let local = info_json(s(&st), &[]);
    let remote = info_json(&url, &[]);
    assert_eq!(local, remote);
    assert!(local["levels"][0]["stats"]["bricks"].as_u64().unwrap() > 0);

    // The same render, read from disk and over HTTP, to the bit.
    let args = [
        "--size",
        "96x64",
        "--backend",
        "cpu",
        "--memory",
        "256MiB",
        "--quiet",
    ];
    let (a, b) = (dir.path().join("local.png"), dir.path().join("remote.png"));
    ok(&bin()
        .args(["render", s(&st), "-o", s(&a)])
        .args(args)
        .output()
        .unwrap());
    let o = bin()
        .args(["render", &url, "-o", s(&b)])
        .args(args)
        .output()
        .unwrap();
    let out = ok(&o);
    assert!(!out.contains("could not load"), "{out}");
    let (pa, pb) = (png_rgba(&a), png_rgba(&b));
    assert!(pa.iter().any(|&v| v != 0), "the image is empty");
    assert_eq!(pa, pb, "the remote render differs from the local one");

    // A store converted from the URL holds the same voxels.
    let copy = dir.path().join("copy.ome.zarr");
    ok(&run(&[
        "convert",
        &url,
        s(&copy),
        "--brick",
        "32",
        "--shard",
        "64",
        "--quiet",
    ]));
    let c = bin()
        .args(["render", s(&copy), "-o", s(&dir.path().join("copy.png"))])
        .args(args)
        .output()
        .unwrap();
    ok(&c);
    assert_eq!(png_rgba(&dir.path().join("copy.png")), pa);

    // The server logged ranged reads.
    assert!(sv.log.lock().unwrap().contains(" 206 "));
}

#[test]
fn ranges_etags_and_cors() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let sv = serve(&[&st], &["--quiet"]);
    let p = sv.port;
    let file = std::fs::read(st.join("0/c/0/0/0")).unwrap();
    let n = file.len();
    assert!(
        n > 32 << 10,
        "a shard above tiny_http's chunking threshold (32 KiB)"
    );

    let (st0, h, body) = http(p, "GET", "/m.ome.zarr/0/c/0/0/0", &[]);
    assert_eq!(st0, 200);
    assert_eq!(body, file);
    assert_eq!(get(&h, "content-length"), Some(n.to_string().as_str()));
    assert_eq!(get(&h, "accept-ranges"), Some("bytes"));
    let etag = get(&h, "etag").unwrap().to_string();

    let (st1, h, body) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("Range", "bytes=10-19")],
    );
    assert_eq!(st1, 206);
    assert_eq!(body, &file[10..20]);
    assert_eq!(
        get(&h, "content-range"),
        Some(format!("bytes 10-19/{n}").as_str())
    );
    assert_eq!(get(&h, "content-length"), Some("10"));

    let (_, _, body) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("Range", "bytes=-100")],
    );
    assert_eq!(body, &file[n - 100..]);
    let (st2, h, _) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("Range", &format!("bytes={n}-"))],
    );
    assert_eq!(st2, 416);
    assert_eq!(
        get(&h, "content-range"),
        Some(format!("bytes */{n}").as_str())
    );

    let (st3, h, body) = http(p, "HEAD", "/m.ome.zarr/0/c/0/0/0", &[]);
    assert_eq!(st3, 200);
    assert!(body.is_empty());
    assert_eq!(get(&h, "content-length"), Some(n.to_string().as_str()));

    let (st4, _, body) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("If-None-Match", &etag)],
    );
    assert_eq!(st4, 304);
    assert!(body.is_empty());
    let (st5, _, _) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("If-None-Match", "\"other\"")],
    );
    assert_eq!(st5, 200);

    let (st6, h, _) = http(
        p,
        "OPTIONS",
        "/m.ome.zarr/zarr.json",
        &[
            ("Origin", "http://example.org"),
            ("Access-Control-Request-Method", "GET"),
            ("Access-Control-Request-Headers", "range"),
        ],
    );
    assert_eq!(st6, 204);
    // Pages of other origins may not read across origins (no token, no
    // --allow-origin); loopback ones may.
    assert_eq!(get(&h, "access-control-allow-origin"), None);
    let (st6, h, _) = http(
        p,
        "OPTIONS",
        "/m.ome.zarr/zarr.json",
        &[
            ("Origin", "http://localhost:5173"),
            ("Access-Control-Request-Method", "GET"),
            ("Access-Control-Request-Headers", "range"),
        ],
    );
    assert_eq!(st6, 204);
    assert_eq!(
        get(&h, "access-control-allow-origin"),
        Some("http://localhost:5173")
    );
    assert!(get(&h, "access-control-allow-methods")
        .unwrap()
        .contains("GET"));
    assert!(get(&h, "access-control-allow-headers")
        .unwrap()
        .contains("Range"));
    let (_, h, _) = http(
        p,
        "GET",
        "/m.ome.zarr/zarr.json",
        &[("Origin", "http://127.0.0.1:9")],
    );
    let exposed = get(&h, "access-control-expose-headers").unwrap();
    for k in ["Content-Range", "Accept-Ranges", "Content-Length"] {
        assert!(exposed.contains(k), "{exposed}");
    }
    let (_, _, body) = http(p, "GET", "/", &[]);
    assert!(String::from_utf8_lossy(&body).contains("m.ome.zarr"));
    let store_dir = st.clone();
    // A name that is not loopback (a page's own name pointed at 127.0.0.1:
    // DNS rebinding) is refused without a token; loopback names pass.
    for (host, want) in [
        ("attacker.example", 421),
        ("attacker.example:8000", 421),
        ("127.0.0.1:8000", 200),
        ("[::1]:8000", 200),
        ("LOCALHOST", 200),
    ] {
        let (st, _, body) = http(p, "GET", "/", &[("Host", host)]);
        assert_eq!(st, want, "{host}");
        assert_eq!(
            String::from_utf8_lossy(&body).contains("m.ome.zarr"),
            want == 200
        );
    }
    // Preconditions: If-Match on another ETag is 412; If-Range on
    // another ETag (or a date) gives the whole file, on this one the range.
    let (st, _, _) = http(
        p,
        "GET",
        "/m.ome.zarr/0/c/0/0/0",
        &[("If-Match", "\"old\"")],
    );
    assert_eq!(st, 412);
    let (st, _, _) = http(p, "GET", "/m.ome.zarr/0/c/0/0/0", &[("If-Match", &etag)]);
    assert_eq!(st, 200);
    for (validator, want, len) in [
        ("\"old\"", 200, n),
        ("Tue, 01 Dec 2026 00:00:00 GMT", 200, n),
        (etag.as_str(), 206, 4),
    ] {
        let (st, _, body) = http(
            p,
            "GET",
            "/m.ome.zarr/0/c/0/0/0",
            &[("Range", "bytes=0-3"), ("If-Range", validator)],
        );
        assert_eq!((st, body.len()), (want, len), "If-Range {validator}");
    }
    // --allow-origin lets a named origin (or any, `*`) read across origins.
    for (allow, origin, want) in [
        (
            "http://example.org",
            "http://example.org",
            Some("http://example.org"),
        ),
        ("http://example.org", "http://other.example", None),
        ("*", "http://other.example", Some("*")),
    ] {
        let sv2 = serve(&[&store_dir], &["--quiet", "--allow-origin", allow]);
        let (_, h, _) = http(
            sv2.port,
            "GET",
            "/m.ome.zarr/zarr.json",
            &[("Origin", origin)],
        );
        assert_eq!(
            get(&h, "access-control-allow-origin"),
            want,
            "{allow} {origin}"
        );
    }

    // SIGTERM: the server stops by itself, with status 0.
    let mut sv = sv;
    let pid = sv.child.id().to_string();
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(st) = sv.child.try_wait().unwrap() {
            break st;
        }
        assert!(t0.elapsed().as_secs() < 10, "serve did not stop on SIGTERM");
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    assert!(status.success(), "{status:?}");
}

#[test]
fn traversal_writes_and_tokens_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let secret = "the secret outside the served store";
    std::fs::write(dir.path().join("secret.txt"), secret).unwrap();
    std::os::unix::fs::symlink(dir.path().join("secret.txt"), st.join("link.txt")).unwrap();
    std::os::unix::fs::symlink(dir.path(), st.join("up")).unwrap();
    // A symlink inside the store to inside the store is fine.
    std::os::unix::fs::symlink(st.join("zarr.json"), st.join("inner.json")).unwrap();
    let sv = serve(&[&st], &["--token", "s3cret-token"]);
    let p = sv.port;
    let auth = [("Authorization", "Bearer s3cret-token")];

    let (code, _, body) = http(p, "GET", "/m.ome.zarr/inner.json", &auth);
    assert_eq!(code, 200);
    assert_eq!(body, std::fs::read(st.join("zarr.json")).unwrap());
    for path in [
        "/m.ome.zarr/../secret.txt",
        "/m.ome.zarr/%2e%2e/secret.txt",
        "/m.ome.zarr/%2E%2E%2Fsecret.txt",
        "/m.ome.zarr/%252e%252e/secret.txt",
        "/m.ome.zarr/..%2fsecret.txt",
        "/m.ome.zarr/./../secret.txt",
        "/m.ome.zarr/link.txt",
        "/m.ome.zarr/up/secret.txt",
        "/m.ome.zarr//etc/passwd",
        "/..%5c..%5csecret.txt",
        "/secret.txt",
        "/m.ome.zarr/0",
    ] {
        let (code, _, body) = http(p, "GET", path, &auth);
        assert!(code == 403 || code == 404, "{path}: {code}");
        assert!(
            !String::from_utf8_lossy(&body).contains(secret),
            "{path} leaked"
        );
    }
    for m in ["PUT", "POST", "DELETE", "PATCH"] {
        let (code, h, _) = http(p, m, "/m.ome.zarr/zarr.json", &auth);
        assert_eq!(code, 405, "{m}");
        assert!(get(&h, "allow").unwrap().contains("GET"));
    }
    assert!(st.join("zarr.json").exists());
    let (code, _, _) = http(p, "GET", "/m.ome.zarr/zarr.json", &[]);
    assert_eq!(code, 401);
    let (code, _, _) = http(
        p,
        "GET",
        "/m.ome.zarr/zarr.json",
        &[("Authorization", "Bearer wrong-token!")],
    );
    assert_eq!(code, 401);
    let (code, _, _) = http(
        p,
        "GET",
        "/m.ome.zarr/zarr.json",
        &[("Authorization", "Bearer s3cret-tokem")],
    );
    assert_eq!(code, 401);
    // The scheme's name in any case; another scheme is not a token.
    for (v, want) in [
        ("bearer s3cret-token", 200),
        ("BEARER  s3cret-token ", 200),
        ("Basic s3cret-token", 401),
        ("Bearers3cret-token", 401),
    ] {
        let (code, _, _) = http(p, "GET", "/m.ome.zarr/zarr.json", &[("Authorization", v)]);
        assert_eq!(code, want, "{v:?}");
    }

    // Reading through brickyard: without the token it says 401, with it it reads.
    let url = format!("http://127.0.0.1:{p}/m.ome.zarr");
    let o = bin()
        .args(["info", &url])
        .env_remove("BRICKYARD_TOKEN")
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("401") && e.contains(&url), "{e}");
    assert!(
        e.contains("BRICKYARD_TOKEN") && !e.contains("--token") && !e.contains("refused: check"),
        "{e}"
    );
    // A wrong token is said to be wrong, not missing.
    let o = bin()
        .args(["info", &url])
        .env("BRICKYARD_TOKEN", "not-the-token-at-all")
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("the token given was refused: check BRICKYARD_TOKEN"),
        "{e}"
    );
    assert_eq!(
        info_json(&url, &[("BRICKYARD_TOKEN", "s3cret-token")]),
        info_json(s(&st), &[])
    );
    drop(sv);

    // A public bind needs a token; the error says so and nothing listens.
    let o = run(&["serve", s(&st), "--bind", "0.0.0.0", "--port", "0"]);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("--token") && e.contains("0.0.0.0"), "{e}");
    let f = dir.path().join("empty-token");
    std::fs::write(&f, "\n").unwrap();
    let o = run(&[
        "serve",
        s(&st),
        "--bind",
        "0.0.0.0",
        "--port",
        "0",
        "--token-file",
        s(&f),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("empty"));
}

#[test]
fn missing_stores_and_unreachable_servers_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let sv = serve(&[&st], &["--quiet"]);
    let o = run(&[
        "info",
        &format!("http://127.0.0.1:{}/nothing.zarr", sv.port),
    ]);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    // Not found, as Python's open says it (it said "not a Zarr store").
    assert!(
        e.contains("nothing.zarr")
            && e.contains("not found (HTTP 404 for zarr.json, .zgroup and .zarray)"),
        "{e}"
    );
    // A port nobody listens on: connection refused, retried, then an error
    // naming the URL.
    let free = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{free}/m.ome.zarr");
    let o = bin()
        .args(["info", &url])
        .env("BRICKYARD_HTTP_RETRIES", "1")
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains(&url) && e.contains("connection"), "{e}");
    let o = bin()
        .args(["info", &url])
        .env("BRICKYARD_HTTP_RETRIES", "x")
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("BRICKYARD_HTTP_RETRIES"));
}

/// `serve` refuses at start, naming it, a path it could serve nothing
/// from: one that does not exist, a file, an empty folder, a folder of
/// other things (also beside a good store); a store and a folder of stores
/// are served.
#[test]
fn serve_refuses_folders_without_a_store() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let coll = d.join("coll");
    std::fs::create_dir(&coll).unwrap();
    let st = coll.join("a.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&st),
        "--size",
        "16",
        "--brick",
        "8",
        "--shard",
        "16",
        "--quiet",
    ]));
    let empty = d.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let notes = d.join("notes");
    std::fs::create_dir_all(notes.join("sub")).unwrap();
    std::fs::write(notes.join("a.txt"), "not a store").unwrap();
    let file = d.join("afile");
    std::fs::write(&file, "hi").unwrap();
    let gone = d.join("gone");
    for (paths, named, why) in [
        (vec![&gone], &gone, "no such folder"),
        (vec![&file], &file, "not a folder"),
        (vec![&empty], &empty, "holds no Zarr store"),
        (vec![&notes], &notes, "holds no Zarr store"),
        (vec![&st, &empty], &empty, "holds no Zarr store"),
    ] {
        // A server that starts anyway would run until killed: wait a while.
        let mut child = bin()
            .arg("serve")
            .args(&paths)
            .args(["--port", "0"])
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        while child.try_wait().unwrap().is_none() {
            if t0.elapsed() > std::time::Duration::from_secs(30) {
                let _ = child.kill();
                let _ = child.wait();
                panic!("serve {paths:?} started");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let o = child.wait_with_output().unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "serve {paths:?}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        assert!(
            e.contains(s(named)) && e.contains(why),
            "{e:?}: {named:?}, {why:?}"
        );
    }
    // Origins no browser sends (a port past 65535 was taken).
    for (origin, why) in [
        ("http://x:99999", "is not 1 to 65535"),
        ("http://x:0", "is not 1 to 65535"),
        ("http://[::1]:99999", "is not 1 to 65535"),
        ("x.org", "expected * or scheme://host[:port]"),
    ] {
        let o = run(&["serve", s(&st), "--port", "0", "--allow-origin", origin]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(why), "{origin}: {e}");
    }
    // The store itself, and the folder it is in.
    for (served, path) in [
        (&st, "/a.ome.zarr/zarr.json"),
        (&coll, "/coll/a.ome.zarr/zarr.json"),
    ] {
        let sv = serve(&[served], &["--quiet"]);
        let (status, _, body) = http(sv.port, "GET", path, &[]);
        assert_eq!(status, 200, "{path}");
        assert_eq!(body, std::fs::read(st.join("zarr.json")).unwrap());
    }
}

/// The viewer on a URL: a view it saves, once complete, equals `render`
/// of the local store with the same camera and transfer function.
#[test]
fn viewer_on_a_url_equals_local_render() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let sv = serve(&[&st], &["--quiet"]);
    let url = format!("http://127.0.0.1:{}/m.ome.zarr", sv.port);
    let p = |n: &str| dir.path().join(n);
    let script = format!(
        "size 3d 96 80\nwait-complete 300\nscreenshot 3d {v}.png\nsave-view 3d {v}\nquit\n",
        v = s(&p("v"))
    );
    let script_file = p("s.txt");
    std::fs::write(&script_file, script).unwrap();
    let args = [
        "view",
        &url,
        "--script",
        s(&script_file),
        "--backend",
        "cpu",
        "--pool",
        "16MiB",
    ];
    let mut cmd = if std::env::var_os("DISPLAY").is_some() {
        let mut c = bin();
        c.args(args);
        c
    } else {
        // The viewer tests (tests/view.rs) say how a display is found;
        // here xvfb-run is required.
        let mut c = Command::new("xvfb-run");
        c.args([
            "-a",
            "-s",
            "-screen 0 1280x800x24",
            env!("CARGO_BIN_EXE_brickyard"),
        ])
        .args(args);
        c
    };
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "view: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let view_args = std::fs::read_to_string(p("v.args")).unwrap();
    let reference = p("ref.png");
    ok(&bin()
        .args(["render", s(&st)])
        .args(view_args.lines())
        .args([
            "--out",
            s(&reference),
            "--pool",
            "16MiB",
            "--backend",
            "cpu",
            "--quiet",
        ])
        .output()
        .unwrap());
    let (a, b) = (png_rgba(&p("v.png")), png_rgba(&reference));
    assert_eq!(a.len(), b.len());
    assert!(a.iter().any(|&v| v != 0), "the view is empty");
    let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
    assert!(
        worst <= 1,
        "the viewer over HTTP and render differ by {worst}"
    );
}

/// Frames of the render endpoint: read a status and its image.
fn ws_frame(
    ws: &mut tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>,
) -> (serde_json::Value, Vec<u8>) {
    loop {
        match ws.read().unwrap() {
            tungstenite::Message::Text(t) => {
                let m: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                assert!(m.get("error").is_none(), "server error: {m}");
                let img = match ws.read().unwrap() {
                    tungstenite::Message::Binary(b) => b.to_vec(),
                    other => panic!("expected an image after {m}, got {other:?}"),
                };
                return (m, img);
            }
            tungstenite::Message::Close(_) => panic!("the server closed the session"),
            _ => {}
        }
    }
}

/// The port of a `serve --render`'s sessions, from its log.
fn render_port(srv: &Served) -> u16 {
    let log = || srv.log.lock().unwrap().clone();
    for _ in 0..100 {
        if let Some(p) = log()
            .split("/render")
            .next()
            .and_then(|l| l.rsplit(':').next())
            .and_then(|p| p.parse().ok())
        {
            return p;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    panic!("no render port in {}", log())
}

fn png_bytes_rgba(b: &[u8]) -> (u32, u32, Vec<u8>) {
    let dec = png::Decoder::new(std::io::Cursor::new(b.to_vec()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// Remote rendering: a client sends a view (camera, transfer function,
/// window, size) over the WebSocket; the frames stream back, JPEG while
/// incomplete, and the final PNG equals `brickyard render` of the same view
/// within 1/255. A second view in the same session is drawn too; a bad
/// message gets an error and the session goes on; sessions beyond the limit
/// and a wrong token are refused at the handshake; the page is served.
#[test]
fn a_new_remote_view_is_previewed_smaller_then_drawn_whole() {
    // A cold 512 × 400 DVR on the CPU: its first frames come at half the
    // width and height (what `render`'s request pass draws) while the
    // bricks load, marked as previews; the last frame is the whole image,
    // equal to render's. (Full frames of stand-ins came first, each as
    // slow as a complete one or slower.)
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path());
    let cam = d.path().join("cam.json");
    let size = ["--size", "512x400", "--tf", "hot", "--window", "0,255"];
    ok(&run(&[
        &["render", s(&st), "--save-camera", s(&cam)][..],
        &size,
        &[
            "--out",
            s(&d.path().join("a.png")),
            "--backend",
            "cpu",
            "--quiet",
        ],
    ]
    .concat()));
    let want = png_rgba(&d.path().join("a.png"));
    let srv = serve(&[&st], &["--render", "--backend", "cpu", "--max-fps", "50"]);
    let url = format!("ws://127.0.0.1:{}/render", render_port(&srv));
    let (mut ws, _) = tungstenite::connect(url.as_str()).unwrap();
    let camera: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cam).unwrap()).unwrap();
    let view = serde_json::json!({"store": "m.ome.zarr", "mode": "dvr", "tf": "hot",
        "window": [0, 255], "size": [512, 400], "camera": camera});
    ws.send(tungstenite::Message::Text(view.to_string().into()))
        .unwrap();
    let mut seen = vec![];
    let last = loop {
        let (m, img) = ws_frame(&mut ws);
        seen.push(m.clone());
        if m["final"] == true {
            break img;
        }
    };
    let previews: Vec<_> = seen.iter().filter(|m| m["preview"] == true).collect();
    assert!(!previews.is_empty(), "no preview: {seen:?}");
    for m in &previews {
        assert_eq!(
            (&m["width"], &m["height"]),
            (&256.into(), &200.into()),
            "{m}"
        );
        assert!(m["completeness"].as_f64().unwrap() < 1.0, "{m}");
    }
    // Previews first, then full frames only.
    let first_full = seen.iter().position(|m| m["preview"] != true).unwrap();
    assert!(
        seen[first_full..].iter().all(|m| m["preview"] != true),
        "{seen:?}"
    );
    let (w, h, got) = png_bytes_rgba(&last);
    assert_eq!((w, h), (512, 400));
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(worst <= 1, "the final frame and render differ by {worst}");
}

#[test]
fn remote_rendering_streams_frames_equal_to_render() {
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path());
    let cam = d.path().join("cam.json");
    ok(&run(&[
        "render",
        s(&st),
        "--size",
        "96x80",
        "--save-camera",
        s(&cam),
        "--out",
        s(&d.path().join("a.png")),
        "--tf",
        "hot",
        "--window",
        "0,255",
        "--backend",
        "cpu",
        "--quiet",
    ]));
    let want = png_rgba(&d.path().join("a.png"));
    let srv = serve(
        &[&st],
        &[
            "--render",
            "--render-sessions",
            "1",
            "--backend",
            "cpu",
            "--max-fps",
            "50",
        ],
    );
    let port = render_port(&srv);
    let url = format!("ws://127.0.0.1:{port}/render");
    // A connection that sends nothing holds no session (the one allowed
    // used to be taken before the handshake, by anyone, token or not).
    let _idle = TcpStream::connect(("127.0.0.1", port)).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(200));
    // A page of another origin may not open a session (no token).
    let mut rq = tungstenite::client::IntoClientRequest::into_client_request(url.as_str()).unwrap();
    rq.headers_mut()
        .insert("Origin", "http://attacker.example".parse().unwrap());
    match tungstenite::connect(rq) {
        Err(tungstenite::Error::Http(r)) => assert_eq!(r.status(), 403),
        other => panic!("a cross-origin page was let in: {:?}", other.map(|_| ())),
    }
    let (mut ws, _) = tungstenite::connect(url.as_str()).unwrap();
    let camera: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cam).unwrap()).unwrap();
    let view = serde_json::json!({"store": "m.ome.zarr", "mode": "dvr", "tf": "hot",
        "window": [0, 255], "size": [96, 80], "camera": camera});
    ws.send(tungstenite::Message::Text(view.to_string().into()))
        .unwrap();
    let mut frames = 0;
    let last = loop {
        let (m, img) = ws_frame(&mut ws);
        frames += 1;
        if m["final"] == true {
            assert_eq!(m["format"], "png");
            assert_eq!(m["complete"], true, "{m}");
            break img;
        }
        assert_eq!(m["format"], "jpeg");
        assert_eq!(&img[..2], &[0xff, 0xd8], "not a JPEG");
    };
    let (w, h, got) = png_bytes_rgba(&last);
    assert_eq!((w, h), (96, 80));
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(
        worst <= 1,
        "remote frame and render differ by {worst} after {frames} frames"
    );
    assert!(
        got.chunks(4).filter(|p| p[0] > 20).count() > 96 * 80 / 20,
        "nearly black"
    );
    // A bad message: an error, and the session goes on.
    ws.send(tungstenite::Message::Text(r#"{"mode": "volume"}"#.into()))
        .unwrap();
    match ws.read().unwrap() {
        tungstenite::Message::Text(t) => assert!(t.as_str().contains("mode"), "{t}"),
        other => panic!("expected an error, got {other:?}"),
    }
    // An empty message and a zoom of nothing are answered, not drawn.
    for (bad, word) in [
        ("{}", "empty"),
        (r#"{"zoom": 0}"#, "zoom"),
        (r#"{"zoom": -1}"#, "zoom"),
    ] {
        ws.send(tungstenite::Message::Text(bad.into())).unwrap();
        match ws.read().unwrap() {
            tungstenite::Message::Text(t) => {
                assert!(
                    t.as_str().contains("error") && t.as_str().contains(word),
                    "{bad}: {t}"
                )
            }
            other => panic!("{bad}: expected an error, got {other:?}"),
        }
    }
    // Another view (orbit and a MIP) in the same session.
    let orbit = serde_json::json!({"camera": null, "azimuth": 120, "elevation": 10, "mode": "mip"});
    ws.send(tungstenite::Message::Text(orbit.to_string().into()))
        .unwrap();
    loop {
        let (m, img) = ws_frame(&mut ws);
        if m["final"] == true {
            let (_, _, px) = png_bytes_rgba(&img);
            assert!(px != got, "the new view is the old one");
            break;
        }
    }
    // One session at most: a second is refused while this one lives.
    match tungstenite::connect(url.as_str()) {
        Err(tungstenite::Error::Http(r)) => assert_eq!(r.status(), 503),
        other => panic!("a second session was not refused: {:?}", other.map(|_| ())),
    }
    drop(ws);
    // The thin client's page names the render port.
    let (status, _, body) = http(srv.port, "GET", "/remote", &[]);
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&body).contains(&format!(":{port}/render")));
    // A token protects the endpoint.
    let srv2 = serve(
        &[&st],
        &["--render", "--token", "sesame", "--backend", "cpu"],
    );
    let mut port2 = None;
    for _ in 0..100 {
        port2 = srv2
            .log
            .lock()
            .unwrap()
            .split("/render")
            .next()
            .and_then(|l| l.rsplit(':').next())
            .and_then(|p| p.parse::<u16>().ok());
        if port2.is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let port2 = port2.expect("render port");
    match tungstenite::connect(format!("ws://127.0.0.1:{port2}/render?token=wrong").as_str()) {
        Err(tungstenite::Error::Http(r)) => assert_eq!(r.status(), 401),
        other => panic!("a wrong token was not refused: {:?}", other.map(|_| ())),
    }
    assert!(
        tungstenite::connect(format!("ws://127.0.0.1:{port2}/render?token=sesame").as_str())
            .is_ok()
    );
    // The token as the HTTP server takes it, in an Authorization header.
    let mut rq = tungstenite::client::IntoClientRequest::into_client_request(
        format!("ws://127.0.0.1:{port2}/render").as_str(),
    )
    .unwrap();
    rq.headers_mut()
        .insert("Authorization", "Bearer sesame".parse().unwrap());
    assert!(tungstenite::connect(rq).is_ok());
}

/// The thin client in a headless browser (Debian's `chromium`): the page
/// at /remote connects, draws the view, drags it with mouse events once it
/// is complete and reports the dragged view's final frame to the server's
/// log. `BRICKYARD_SKIP_BROWSER=1` opts out where no browser is installed.
#[test]
fn the_remote_page_drags_the_view_in_a_headless_browser() {
    let chromium = ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|b| {
            Command::new(b)
                .arg("--version")
                .output()
                .is_ok_and(|o| o.status.success())
        });
    let Some(chromium) = chromium else {
        if std::env::var("BRICKYARD_SKIP_BROWSER").as_deref() == Ok("1") {
            eprintln!("skipped: no chromium and BRICKYARD_SKIP_BROWSER=1");
            return;
        }
        panic!("this test needs chromium (apt-get install chromium); BRICKYARD_SKIP_BROWSER=1 opts out");
    };
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path());
    let srv = serve(&[&st], &["--render", "--backend", "cpu"]);
    let profile = d.path().join("profile");
    let url = format!(
        "http://127.0.0.1:{}/remote?selftest=1&store=m.ome.zarr",
        srv.port
    );
    let mut browser = Command::new(chromium)
        .args([
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--no-first-run",
            "--window-size=800,700",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(&url)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    let report = loop {
        let log = srv.log.lock().unwrap().clone();
        if let Some(l) = log.lines().find(|l| l.contains("render client reports:")) {
            break l.to_string();
        }
        if t0.elapsed().as_secs() > 180 {
            let _ = browser.kill();
            panic!("no report from the page after 180 s; server log:\n{log}");
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
    };
    let _ = browser.kill();
    let _ = browser.wait();
    assert!(report.contains("selftest ok"), "{report}");
    assert!(report.contains("final complete 640x480"), "{report}");
    // The drag turned the camera (from azimuth 30).
    assert!(!report.contains("azimuth 30 "), "{report}");
    let lit: f64 = report
        .rsplit("lit ")
        .next()
        .and_then(|x| x.trim().parse().ok())
        .unwrap_or_else(|| panic!("{report}"));
    assert!(lit > 0.02, "the dragged view is nearly black: {report}");
}

/// `s3://` locations against an S3-compatible endpoint (`--s3-endpoint`,
/// path style: `endpoint/bucket/key`): here the store server, whose store
/// names stand for buckets. Signed (credentials in the environment: the
/// server ignores the signature's query, the addresses must still be
/// right) and anonymous reads equal local reads; bad settings are clear
/// errors naming the flag or variable. The signature itself is checked
/// against Amazon's documented example in `brickyard-store`, and against
/// an independent S3 server by the interop script when it is installed.
#[test]
fn s3_locations_read_through_an_endpoint_equal_local_reads() {
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let sv = serve(&[&st], &[]);
    let endpoint = format!("http://127.0.0.1:{}", sv.port);
    let local = info_json(s(&st), &[]);
    let args = ["--size", "96x64", "--backend", "cpu", "--quiet"];
    let a = dir.path().join("local.png");
    ok(&bin()
        .args(["render", s(&st), "-o", s(&a)])
        .args(args)
        .output()
        .unwrap());
    let pa = png_rgba(&a);
    assert!(pa.iter().any(|&v| v != 0), "the image is empty");
    let creds: &[(&str, &str)] = &[
        ("AWS_ACCESS_KEY_ID", "AKIDEXAMPLE"),
        (
            "AWS_SECRET_ACCESS_KEY",
            "wJalrXUtnFEMI/K7MDENG+bPxRfiCYEXAMPLEKEY",
        ),
    ];
    for (case, env, flags) in [
        ("anonymous", &[][..], vec!["--s3-endpoint", &endpoint]),
        ("signed", creds, vec!["--s3-endpoint", &endpoint]),
        (
            "signed, endpoint from the environment",
            &[
                creds[0],
                creds[1],
                ("AWS_ENDPOINT_URL", endpoint.as_str()),
                ("AWS_REGION", "eu-west-1"),
            ][..],
            vec![],
        ),
    ] {
        // Key prefixes: the bucket's root, with and without a slash.
        for loc in ["s3://m.ome.zarr", "s3://m.ome.zarr/"] {
            let mut c = aws_bin();
            c.args(["info", loc, "--json"]).args(&flags);
            for (k, v) in env {
                c.env(k, v);
            }
            assert_eq!(info_json_of(c), local, "{case}: info of {loc}");
        }
        let b = dir.path().join("s3.png");
        let mut c = aws_bin();
        c.args(["render", "s3://m.ome.zarr", "-o", s(&b)])
            .args(args)
            .args(&flags);
        for (k, v) in env {
            c.env(k, v);
        }
        let out = ok(&c.output().unwrap());
        assert!(!out.contains("could not load"), "{case}: {out}");
        assert_eq!(
            png_rgba(&b),
            pa,
            "{case}: the render differs from the local one"
        );
    }
    // The requests were path style, and signed where credentials were set.
    let log = sv.log.lock().unwrap().clone();
    assert!(log.contains("/m.ome.zarr/zarr.json"), "{log}");
    // A bucket that is not there; bad names and settings.
    let o = aws_bin()
        .args(["info", "s3://nothing.zarr", "--s3-endpoint", &endpoint])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("s3://nothing.zarr"), "{e}");
    for (args, env, want) in [
        (
            vec!["info", "s3://Bad_Name/x", "--s3-endpoint", &endpoint],
            vec![],
            "bucket name",
        ),
        (
            vec!["info", "s3://m.ome.zarr", "--s3-endpoint", "localhost:9"],
            vec![],
            "--s3-endpoint",
        ),
        (
            vec!["info", "s3://m.ome.zarr", "--s3-region", "eu west"],
            vec![],
            "--s3-region",
        ),
        (
            vec!["info", "s3://m.ome.zarr", "--s3-endpoint", &endpoint],
            vec![("AWS_ACCESS_KEY_ID", "k")],
            "AWS_SECRET_ACCESS_KEY",
        ),
    ] {
        let mut c = aws_bin();
        c.args(&args);
        for (k, v) in env {
            c.env(k, v);
        }
        let o = c.output().unwrap();
        assert!(!o.status.success(), "{args:?} succeeded");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(want), "{args:?}: {e}");
    }
}

/// The binary with no AWS settings from the caller's environment.
fn aws_bin() -> Command {
    let mut c = bin();
    for (k, _) in std::env::vars() {
        if k.starts_with("AWS_") {
            c.env_remove(k);
        }
    }
    c
}

/// A served folder of stores lists each store by its path, and the web
/// client's link opens one of them (not the folder, which is no store).
#[test]
fn a_folder_of_stores_is_listed_store_by_store() {
    let d = tempfile::tempdir().unwrap();
    let folder = d.path().join("st");
    std::fs::create_dir(&folder).unwrap();
    for name in ["b.ome.zarr", "a.ome.zarr"] {
        let store = folder.join(name);
        std::fs::create_dir(&store).unwrap();
        std::fs::write(
            store.join("zarr.json"),
            r#"{"zarr_format":3,"node_type":"group"}"#,
        )
        .unwrap();
    }
    // A stand-in bundle: the page is not opened here.
    let dist = d.path().join("dist");
    std::fs::create_dir(&dist).unwrap();
    for f in [
        "index.html",
        "app.js",
        "brickyard_web.js",
        "brickyard_web_bg.wasm",
    ] {
        std::fs::write(dist.join(f), "x").unwrap();
    }
    let sv = serve(&[&folder], &["--web", "--web-dist", s(&dist)]);
    let link = |log: &str| {
        log.lines()
            .find_map(|l| l.split("#store=../").nth(1).map(str::to_string))
    };
    let until = Instant::now() + Duration::from_secs(10);
    while link(&sv.log.lock().unwrap()).is_none() && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    let log = sv.log.lock().unwrap().clone();
    assert!(
        log.starts_with("serving 2 store(s)") && log.contains("/st/a.ome.zarr/ /st/b.ome.zarr/"),
        "{log}"
    );
    let store = link(&log).unwrap_or_else(|| panic!("no link in {log}"));
    assert_eq!(store, "st/a.ome.zarr/");
    let (status, _, _) = http(sv.port, "GET", &format!("/{store}zarr.json"), &[]);
    assert_eq!(status, 200, "the link's store is served");
    // `/` lists the stores by their paths (it listed the folder, `st`,
    // which the render page offered and could not open).
    let (status, _, body) = http(sv.port, "GET", "/", &[]);
    assert_eq!(status, 200);
    let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        v["stores"],
        serde_json::json!(["st/a.ome.zarr", "st/b.ome.zarr"]),
        "{v}"
    );
}

/// A served folder serves the stores found in it at start and nothing
/// else: not its other files, not hidden files (Zarr's `.zarray` … aside),
/// not a store's links leading out of that store (even into the folder),
/// and a store that is a link out of the folder is neither listed nor
/// served (the start says so).
#[test]
fn a_served_folder_serves_its_stores_only() {
    let d = tempfile::tempdir().unwrap();
    let folder = d.path().join("coll");
    std::fs::create_dir(&folder).unwrap();
    let group = r#"{"zarr_format":3,"node_type":"group"}"#;
    for name in ["a.ome.zarr", "b.ome.zarr"] {
        let store = folder.join(name);
        std::fs::create_dir(&store).unwrap();
        std::fs::write(store.join("zarr.json"), group).unwrap();
    }
    let a = folder.join("a.ome.zarr");
    std::fs::write(a.join(".zattrs"), "{}").unwrap();
    std::fs::write(a.join(".secret"), "SECRET-dot-in-store").unwrap();
    std::fs::create_dir(a.join(".git")).unwrap();
    std::fs::write(a.join(".git").join("config"), "SECRET-git").unwrap();
    std::fs::write(folder.join("secret.txt"), "SECRET-in-folder").unwrap();
    std::fs::create_dir(folder.join(".aws")).unwrap();
    std::fs::write(folder.join(".aws").join("credentials"), "SECRET-aws").unwrap();
    std::os::unix::fs::symlink(folder.join("secret.txt"), a.join("out.txt")).unwrap();
    std::os::unix::fs::symlink(folder.join("b.ome.zarr"), a.join("sibling")).unwrap();
    std::os::unix::fs::symlink(a.join(".secret"), a.join("dot-link")).unwrap();
    // A store outside the folder, linked into it; a link to a store inside.
    let outside = d.path().join("outside.ome.zarr");
    std::fs::create_dir(&outside).unwrap();
    std::fs::write(outside.join("zarr.json"), group).unwrap();
    std::fs::write(outside.join("data"), "SECRET-outside").unwrap();
    std::os::unix::fs::symlink(&outside, folder.join("ext.ome.zarr")).unwrap();
    std::os::unix::fs::symlink(&a, folder.join("alias.ome.zarr")).unwrap();
    // A hidden store is not served either.
    let hidden = folder.join(".hidden.ome.zarr");
    std::fs::create_dir(&hidden).unwrap();
    std::fs::write(hidden.join("zarr.json"), group).unwrap();

    let sv = serve(&[&folder], &[]);
    let until = Instant::now() + Duration::from_secs(10);
    while !sv.log.lock().unwrap().contains("hidden.ome.zarr") && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    let log = sv.log.lock().unwrap().clone();
    let first = log.lines().next().unwrap();
    assert!(
        first.starts_with("serving 3 store(s)")
            && first.contains("/coll/a.ome.zarr/ /coll/alias.ome.zarr/ /coll/b.ome.zarr/")
            && !first.contains("ext.ome.zarr"),
        "{log}"
    );
    assert!(
        log.lines().any(|l| l.contains("not served")
            && l.contains("ext.ome.zarr")
            && l.contains("outside")),
        "{log}"
    );
    assert!(
        log.lines()
            .any(|l| l.contains("not served") && l.contains(".hidden.ome.zarr")),
        "{log}"
    );
    let p = sv.port;
    for path in [
        "/coll/secret.txt",
        "/coll/.aws/credentials",
        "/coll/%2eaws/credentials",
        "/coll/a.ome.zarr/.secret",
        "/coll/a.ome.zarr/.git/config",
        "/coll/a.ome.zarr/dot-link",
        "/coll/a.ome.zarr/out.txt",
        "/coll/a.ome.zarr/sibling/zarr.json",
        "/coll/ext.ome.zarr/zarr.json",
        "/coll/ext.ome.zarr/data",
        "/coll/.hidden.ome.zarr/zarr.json",
        "/coll",
    ] {
        let (code, _, body) = http(p, "GET", path, &[]);
        assert!(code == 403 || code == 404, "{path}: {code}");
        assert!(
            !String::from_utf8_lossy(&body).contains("SECRET"),
            "{path} leaked"
        );
    }
    for path in [
        "/coll/a.ome.zarr/zarr.json",
        "/coll/a.ome.zarr/.zattrs",
        "/coll/b.ome.zarr/zarr.json",
        "/coll/alias.ome.zarr/zarr.json",
    ] {
        let (code, _, _) = http(p, "GET", path, &[]);
        assert_eq!(code, 200, "{path}");
    }
    drop(sv);

    // A single store: its hidden files are not served either.
    let sv = serve(&[&a], &["--quiet"]);
    for (path, want) in [
        ("/a.ome.zarr/.secret", 403),
        ("/a.ome.zarr/.git/config", 403),
        ("/a.ome.zarr/dot-link", 403),
        ("/a.ome.zarr/.zattrs", 200),
        ("/a.ome.zarr/zarr.json", 200),
    ] {
        let (code, _, _) = http(sv.port, "GET", path, &[]);
        assert_eq!(code, want, "{path}");
    }
}

/// Sends `head` on a new connection and reads what comes back within
/// `wait`: the status line, whether the server closed the connection, and
/// how long it took (the connection stays open on this side).
fn raw_exchange(port: u16, head: &[u8], wait: Duration) -> (String, bool, Duration) {
    let mut c = TcpStream::connect(("127.0.0.1", port)).unwrap();
    let t0 = Instant::now();
    // (The server may close before all of it is sent.)
    let _ = c.write_all(head);
    c.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let mut got = vec![];
    let mut closed = false;
    let mut b = [0u8; 4096];
    while t0.elapsed() < wait {
        match c.read(&mut b) {
            Ok(0) => {
                closed = true;
                break;
            }
            Ok(n) => got.extend_from_slice(&b[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => {
                closed = true;
                break;
            }
            Err(_) => {}
        }
    }
    let status = String::from_utf8_lossy(&got)
        .lines()
        .next()
        .unwrap_or("")
        .to_string();
    (status, closed, t0.elapsed())
}

/// A request with a body (GET and HEAD take none) is refused at once and
/// its connection closed, without waiting for the body: clients that
/// trickle a large body hold no worker; so are heads too large.
#[test]
fn request_bodies_and_huge_heads_are_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("st");
    let st = folder.join("a.ome.zarr");
    std::fs::create_dir_all(&st).unwrap();
    std::fs::write(
        st.join("zarr.json"),
        r#"{"zarr_format":3,"node_type":"group"}"#,
    )
    .unwrap();
    let sv = serve(&[&st], &["--workers", "1"]);
    let p = sv.port;
    let wait = Duration::from_secs(10);
    // Clients holding their bodies back (their connections stay open).
    let mut held = vec![];
    for _ in 0..4 {
        let mut c = TcpStream::connect(("127.0.0.1", p)).unwrap();
        c.write_all(
            b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nContent-Length: 100000000\r\n\r\nx",
        )
        .unwrap();
        held.push(c);
    }
    for (head, want) in [
        (
            &b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nContent-Length: 100000000\r\n\r\nxx"[..],
            "413",
        ),
        (
            b"PUT /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nContent-Length: 18446744073709551615\r\n\r\n",
            "405",
        ),
        (
            b"POST /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello",
            "405",
        ),
        (
            b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello",
            "413",
        ),
        (
            b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nContent-Length: 12x\r\n\r\n",
            "400",
        ),
        // Two Hosts: which one a proxy took is not known.
        (
            b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\nHost: example.org\r\n\r\n",
            "400",
        ),
        // None, in HTTP/1.1 (it was served).
        (b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\n\r\n", "400"),
    ] {
        let (status, closed, took) = raw_exchange(p, head, wait);
        assert!(
            status.starts_with("HTTP/1.1 ") && status.contains(want),
            "{}: {status:?} after {took:?}",
            String::from_utf8_lossy(head)
        );
        assert!(closed && took < Duration::from_secs(5), "{status}: {took:?}");
    }
    // The one worker still answers.
    let t0 = Instant::now();
    let (code, _, body) = http(p, "GET", "/a.ome.zarr/zarr.json", &[]);
    assert_eq!(code, 200);
    assert!(!body.is_empty() && t0.elapsed() < Duration::from_secs(5));
    let (code, _, _) = http(
        p,
        "GET",
        "/a.ome.zarr/zarr.json",
        &[("Content-Length", "0")],
    );
    assert_eq!(code, 200, "an empty body is no body");
    // A folder's path with its slash: not listed, said so (it was 403
    // "path segment refused").
    let (code, _, body) = http(p, "GET", "/a.ome.zarr/", &[]);
    let body = String::from_utf8_lossy(&body);
    assert_eq!(code, 404, "{body}");
    assert!(body.contains("a folder"), "{body}");

    // A head past the limit: 431 and closed, not read on.
    let mut head = b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nHost: localhost\r\n".to_vec();
    for _ in 0..64 {
        head.extend_from_slice(b"X-Pad: ");
        head.extend(std::iter::repeat_n(b'a', 1000));
        head.extend_from_slice(b"\r\n");
    }
    head.extend_from_slice(b"\r\n");
    let (status, closed, took) = raw_exchange(p, &head, wait);
    assert!(
        status.contains("431") && closed,
        "{status:?} after {took:?}"
    );
    let (code, _, _) = http(p, "GET", "/a.ome.zarr/zarr.json", &[]);
    assert_eq!(code, 200);
    drop(held);
}

/// Connections that send nothing (or a head byte by byte) do not shut
/// others out: beyond the limit of open connections the one that has
/// waited longest for a request is closed to make room.
#[test]
fn idle_connections_cannot_exhaust_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let st = dir.path().join("a.ome.zarr");
    std::fs::create_dir_all(&st).unwrap();
    std::fs::write(
        st.join("zarr.json"),
        r#"{"zarr_format":3,"node_type":"group"}"#,
    )
    .unwrap();
    let sv = serve(&[&st], &["--quiet"]);
    let p = sv.port;
    let mut idle = vec![];
    for _ in 0..400 {
        let mut c = TcpStream::connect(("127.0.0.1", p)).unwrap();
        let _ = c.write_all(b"GET /a.ome.zarr/zarr.json HTTP/1.1\r\nX-a: ");
        idle.push(c);
    }
    std::thread::sleep(Duration::from_millis(500));
    let t0 = Instant::now();
    let (code, _, _) = http(p, "GET", "/a.ome.zarr/zarr.json", &[]);
    assert_eq!(code, 200);
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
    // The server holds a bounded number of threads.
    let threads = std::fs::read_dir(format!("/proc/{}/task", sv.child.id()))
        .map(|d| d.count())
        .unwrap_or(0);
    assert!(threads < 300, "{threads} threads");
    drop(idle);
}

#[test]
fn damaged_chunk_paths_are_errors_not_absent_chunks() {
    // Zarr clients read a 404 as "no chunk here" and use the fill value:
    // only a path with nothing there may get one. A folder or a FIFO where
    // a chunk's file should be is damage (403), so a client fails instead
    // of reading zeros.
    let dir = tempfile::tempdir().unwrap();
    let st = store(dir.path());
    let shard = st.join("0/c/0/0/0");
    assert!(shard.is_file());
    std::fs::remove_file(&shard).unwrap();
    std::fs::create_dir(&shard).unwrap();
    let fifo = st.join("0/c/0/0/1");
    std::fs::remove_file(&fifo).unwrap();
    let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let sv = serve(&[&st], &[]);
    for (path, want) in [
        ("/m.ome.zarr/0/c/0/0/0", 403),
        ("/m.ome.zarr/0/c/0/0/1", 403),
        ("/m.ome.zarr/0/c/1/0/0", 200),
        ("/m.ome.zarr/0/c/9/9/9", 404),
        ("/m.ome.zarr/0/zarr.json/c", 404),
    ] {
        let (code, _, _) = http(sv.port, "GET", path, &[]);
        assert_eq!(code, want, "{path}");
    }
    // A client refused a path says the server's reason, not that a token
    // may be needed (the server takes none).
    let url = format!("http://127.0.0.1:{}/m.ome.zarr/../m.ome.zarr", sv.port);
    let o = bin()
        .args(["info", &url])
        .env_remove("BRICKYARD_TOKEN")
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(
        e.contains("403") && e.contains("path segment refused") && !e.contains("TOKEN"),
        "{e}"
    );
}

/// A store an interrupted conversion left (brickyard's `complete: false`
/// in its root zarr.json), given or found in a served folder, is still
/// served, but the start warns of it on stderr, naming it; a complete
/// store and a plain Zarr group get no warning.
#[test]
fn incomplete_stores_are_served_with_a_warning() {
    let d = tempfile::tempdir().unwrap();
    let group = |dir: &Path, attrs: &str| {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(
            dir.join("zarr.json"),
            format!(r#"{{"zarr_format":3,"node_type":"group","attributes":{attrs}}}"#),
        )
        .unwrap();
    };
    let folder = d.path().join("st");
    group(
        &folder.join("done.ome.zarr"),
        r#"{"brickyard":{"complete":true}}"#,
    );
    group(
        &folder.join("half.ome.zarr"),
        r#"{"brickyard":{"complete":false}}"#,
    );
    group(&folder.join("plain.zarr"), "{}");
    let partial = d.path().join("x.ome.zarr.partial");
    group(&partial, r#"{"brickyard":{"version":1,"complete":false}}"#);
    let sv = serve(&[&folder, &partial], &["--quiet"]);
    // Warnings come in URL order: the last one says the listing is done.
    let until = Instant::now() + Duration::from_secs(60);
    while !sv.log.lock().unwrap().contains("/x.ome.zarr.partial/ (") && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    let log = sv.log.lock().unwrap().clone();
    let warnings: Vec<&str> = log.lines().filter(|l| l.starts_with("warning:")).collect();
    assert_eq!(warnings.len(), 2, "{log}");
    for (w, (url, path)) in warnings.iter().zip([
        ("/st/half.ome.zarr/", folder.join("half.ome.zarr")),
        ("/x.ome.zarr.partial/", partial.clone()),
    ]) {
        let path = path.canonicalize().unwrap();
        assert!(
            w.contains(url) && w.contains(s(&path)) && w.contains("INCOMPLETE"),
            "{w}"
        );
    }
    // Served all the same.
    for p in [
        "/st/half.ome.zarr/zarr.json",
        "/x.ome.zarr.partial/zarr.json",
    ] {
        let (status, _, _) = http(sv.port, "GET", p, &[]);
        assert_eq!(status, 200, "{p}");
    }
}

/// Render-session flags are checked at start: a bad --backend or an empty
/// --render-pool was accepted and then every session failed; without
/// --render they changed nothing and were taken silently.
#[test]
fn render_session_flags_are_checked_at_start() {
    let d = tempfile::tempdir().unwrap();
    let st = d.path().join("s.ome.zarr");
    std::fs::create_dir_all(&st).unwrap();
    std::fs::write(
        st.join("zarr.json"),
        r#"{"zarr_format":3,"node_type":"group","attributes":{}}"#,
    )
    .unwrap();
    for (args, words) in [
        (
            vec!["--render", "--backend", "foo"],
            vec!["--backend", "expected auto, gpu or cpu"],
        ),
        (
            vec!["--render", "--render-pool", "0"],
            vec!["--render-pool", "above 0"],
        ),
        (vec!["--backend", "cpu"], vec!["--backend", "give --render"]),
        (
            vec!["--render-pool", "64MiB"],
            vec!["--render-pool", "give --render"],
        ),
        (vec!["--max-fps", "5"], vec!["--max-fps", "give --render"]),
    ] {
        let mut a = vec!["serve", st.to_str().unwrap(), "--port", "0"];
        a.extend(args.iter());
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_brickyard"))
            .args(&a)
            .output()
            .unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{a:?}: {e}");
        for w in words {
            assert!(e.contains(w), "{a:?}: {w:?} not in {e}");
        }
    }
}
