//! `brickyard serve --render`: remote rendering for thin clients. A
//! WebSocket endpoint (its own port, printed at start and written into the
//! `/remote` page) takes views as JSON text messages and streams back the
//! frames of each as the session refines it: JPEG while the view is
//! incomplete, PNG once it is complete (or can get no better), each after
//! a JSON status message. Every connection has its own session of the
//! virtual memory on the server's back end; the sessions of one store share
//! one host cache. Connections beyond `--render-sessions` are refused (503
//! at the handshake), frames are sent at most `--max-fps` a second, and a
//! bearer token, when the server has one, must come as `?token=` (browsers
//! cannot set headers on a WebSocket).
//!
//! A view message: `{"store": "NAME", "mode": "dvr|mip|slice", "tf":
//! PRESET or {transfer function}, "window": [lo, hi], "size": [w, h],
//! "azimuth": deg, "elevation": deg, "zoom": z}` or `"camera": {camera
//! JSON}` instead of the orbit; fields left out keep their last value.
//! `{"report": "…"}` is written to the server's log (the page's self-test
//! uses it). Errors come back as `{"error": "…"}` and the session goes on.

use anyhow::{bail, Context, Result};
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::TransferFunction;
use brickyard_render::budget::{Decision, LodBudget};
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::reference::{RenderMode, RenderParams};
use brickyard_render::Image;
use brickyard_store::import::zarr;
use brickyard_store::VolumeSource;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tungstenite::{Message, WebSocket};

/// What the render endpoint needs.
pub struct RenderSite {
    /// Mount name → store root.
    pub roots: HashMap<String, PathBuf>,
    pub token: Option<String>,
    /// `serve --allow-origin`.
    pub origins: Vec<String>,
    pub backend: String,
    pub sessions: usize,
    pub max_fps: f64,
    /// Brick pool per session.
    pub pool: u64,
    /// Host cache per store (shared by its sessions).
    pub host: u64,
    pub log: bool,
}

/// Host caches by store, made on first use.
type Caches = Arc<Mutex<HashMap<String, Arc<HostCache>>>>;

/// Accept WebSocket connections on `listener` until the process ends.
pub fn serve(listener: TcpListener, site: Arc<RenderSite>) {
    let live = Arc::new(AtomicUsize::new(0));
    let caches: Caches = Arc::default();
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let (site, live, caches) = (site.clone(), live.clone(), caches.clone());
        std::thread::spawn(move || {
            let peer = stream
                .peer_addr()
                .map(|a| a.to_string())
                .unwrap_or_default();
            if let Err(e) = connection(stream, &site, &live, &caches) {
                if site.log {
                    eprintln!("render {peer}: {e:#}");
                }
            }
        });
    }
}

/// The handshake (token, session limit), then the session.
// (The handshake callback's error type is tungstenite's HTTP response.)
#[allow(clippy::result_large_err)]
fn connection(
    stream: TcpStream,
    site: &RenderSite,
    live: &AtomicUsize,
    caches: &Caches,
) -> Result<()> {
    let _ = stream.set_nodelay(true);
    // A client that connects and sends nothing is dropped after 5 s; it
    // never holds a session's slot (taken once the handshake's request is
    // checked).
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    struct Slot<'a>(&'a AtomicUsize, std::cell::Cell<bool>);
    impl Drop for Slot<'_> {
        fn drop(&mut self) {
            if self.1.get() {
                self.0.fetch_sub(1, Ordering::SeqCst);
            }
        }
    }
    let held = Slot(live, std::cell::Cell::new(false));
    // (Borrowed by the handshake's check: held until the session ends.)
    let slot = &held;
    let token = site.token.clone();
    let origins = site.origins.clone();
    let sessions = site.sessions;
    let check = move |rq: &Request, rs: Response| -> std::result::Result<Response, ErrorResponse> {
        let refuse = |code: u16, msg: &str| {
            let mut e = ErrorResponse::new(Some(msg.to_string()));
            *e.status_mut() = tungstenite::http::StatusCode::from_u16(code).expect("valid status");
            e
        };
        if rq.uri().path() != "/render" {
            return Err(refuse(404, "the render endpoint is /render"));
        }
        let header = |k: &str| rq.headers().get(k).and_then(|v| v.to_str().ok());
        if let Some(t) = &token {
            // `?token=` (browsers cannot set headers on a WebSocket) or
            // `Authorization: Bearer`, as the HTTP server takes it.
            let given = rq
                .uri()
                .query()
                .unwrap_or("")
                .split('&')
                .find_map(|kv| kv.strip_prefix("token="))
                .or_else(|| {
                    header("Authorization")
                        .and_then(|v| v.trim().split_once(' '))
                        .filter(|(s, _)| s.eq_ignore_ascii_case("bearer"))
                        .map(|(_, t)| t.trim())
                });
            if given != Some(t.as_str()) {
                return Err(refuse(
                    401,
                    "a valid ?token= (or Authorization: Bearer) is required",
                ));
            }
        } else {
            // No token: only pages of loopback origins (or those allowed)
            // and clients that send no origin, on a loopback host name.
            if header("Origin").is_some_and(|o| !crate::serve::origin_allowed(o, &origins)) {
                return Err(refuse(
                    403,
                    "pages of this origin may not open render sessions (serve --allow-origin)",
                ));
            }
            if header("Host").is_some_and(|h| !crate::serve::loopback_host(h)) {
                return Err(refuse(421, "this server answers loopback host names only"));
            }
        }
        if live.fetch_add(1, Ordering::SeqCst) >= sessions {
            live.fetch_sub(1, Ordering::SeqCst);
            return Err(refuse(503, "too many render sessions; try again later"));
        }
        slot.1.set(true);
        Ok(rs)
    };
    let mut ws = tungstenite::accept_hdr(stream, check)
        .map_err(|e| anyhow::anyhow!("WebSocket handshake: {e}"))?;
    if site.log {
        eprintln!(
            "render: session opened ({} live)",
            live.load(Ordering::SeqCst)
        );
    }
    let r = session(&mut ws, site, caches);
    let _ = ws.close(None);
    let _ = ws.flush();
    if site.log {
        eprintln!("render: session closed");
    }
    r
}

/// The view a client asked for.
#[derive(Clone, Debug, PartialEq)]
struct View {
    store: Option<String>,
    mode: String,
    tf: Value,
    window: Option<[f32; 2]>,
    size: [u32; 2],
    azimuth: f64,
    elevation: f64,
    zoom: f64,
    camera: Option<Value>,
}

impl Default for View {
    fn default() -> View {
        View {
            store: None,
            mode: "dvr".into(),
            tf: Value::String("soft".into()),
            window: None,
            size: [512, 512],
            azimuth: 30.0,
            elevation: 20.0,
            zoom: 1.0,
            camera: None,
        }
    }
}

impl View {
    /// This view with the fields of message `m` applied.
    fn apply(&self, m: &serde_json::Map<String, Value>) -> Result<View> {
        let mut v = self.clone();
        for (k, x) in m {
            let num = || {
                x.as_f64()
                    .filter(|f| f.is_finite())
                    .with_context(|| format!("{k}: expected a number, got {x}"))
            };
            match k.as_str() {
                "store" => v.store = Some(x.as_str().with_context(|| format!("store: expected a name, got {x}"))?.to_string()),
                "mode" => {
                    let s = x.as_str().unwrap_or("");
                    if !["dvr", "mip", "slice"].contains(&s) {
                        bail!("mode: expected dvr, mip or slice, got {x}");
                    }
                    v.mode = s.into();
                }
                "tf" => v.tf = x.clone(),
                "window" => {
                    let w: [f32; 2] = serde_json::from_value(x.clone()).with_context(|| format!("window: expected [lo, hi], got {x}"))?;
                    if !(w[0].is_finite() && w[1].is_finite()) {
                        bail!("window: expected numbers within ±{:e} (the range of 32-bit floats), got {x}", f32::MAX);
                    }
                    if w[0] >= w[1] {
                        bail!("window: expected lo < hi, got {x}");
                    }
                    v.window = Some(w);
                }
                "size" => {
                    let s: [u32; 2] = serde_json::from_value(x.clone()).with_context(|| format!("size: expected [w, h], got {x}"))?;
                    if s[0] == 0 || s[1] == 0 || s[0] > 4096 || s[1] > 4096 {
                        bail!("size: each side from 1 to 4096 pixels, got {x}");
                    }
                    v.size = s;
                }
                "azimuth" => v.azimuth = num()?,
                "elevation" => v.elevation = num()?.clamp(-89.9, 89.9),
                "zoom" => {
                    let z = num()?;
                    if !(z > 0.0 && z <= 100.0) {
                        bail!("zoom: expected a factor above 0 and at most 100, got {x}");
                    }
                    v.zoom = z.max(0.05);
                }
                "camera" => v.camera = if x.is_null() { None } else { Some(x.clone()) },
                other => bail!("unknown field {other:?}; expected store, mode, tf, window, size, azimuth, elevation, zoom, camera or report"),
            }
        }
        Ok(v)
    }
}

/// An open store: its session, back end and scene.
struct Open {
    name: String,
    s: Session,
    backend: brickyard_run::backend::Backend,
    scene: Scene,
    /// The default data window.
    window: (f64, f64),
}

fn open(site: &RenderSite, caches: &Caches, name: &str) -> Result<Open> {
    let root = site
        .roots
        .get(name)
        .with_context(|| format!("store: {name:?} is not served here"))?;
    let l0 = zarr::open(root, 0)?;
    let m = l0.meta().clone();
    let extent = world_extent(m.dims, m.spacing.unwrap_or([1.0; 3]));
    let mut levels = vec![];
    while let Ok(z) = zarr::open(root, levels.len()) {
        levels.push(z.meta().dims);
    }
    let n_levels = levels.len();
    let mut scene = Scene::new(extent, levels);
    let host = caches
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .entry(name.to_string())
        .or_insert_with(|| Arc::new(HostCache::new(site.host)))
        .clone();
    let mut cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: site.pool,
        upload_bytes_per_frame: 64 << 20,
        ..Default::default()
    };
    cfg.request_cap = crate::frames::requests_per_frame(
        site.pool,
        site.host,
        cfg.slot_bytes(m.dtype),
        crate::frames::STREAM_REQUESTS,
    );
    let mut s = Session::with_cache(root, cfg, host, 2)?;
    // A frame waits a little for the bricks it asked for (the session's
    // messages wait meanwhile).
    s.set_batch(Some(brickyard_run::frames::STREAM_LOAD_WAIT));
    s.pin_coarsest(512, Duration::from_secs(120)).map_err(|e| {
        anyhow::anyhow!(
            "serve --render-pool {}: {e}",
            brickyard_store::info::human_bytes(site.pool)
        )
    })?;
    let backend = brickyard_run::backend::Backend::choose(
        &site.backend,
        brickyard_run::backend::GpuUpdate::Device,
        &mut s,
        1,
    )?;
    scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 24)));
    let window = brickyard_run::window::auto_window(root, n_levels, 0)?.unwrap_or((0.0, 1.0));
    Ok(Open {
        name: name.to_string(),
        s,
        backend,
        scene,
        window,
    })
}

/// The render parameters of `v` on store `o`.
fn params(o: &Open, v: &View) -> Result<RenderParams> {
    let extent = o.scene.extent;
    let window = v.window.unwrap_or([o.window.0 as f32, o.window.1 as f32]);
    let tf = match &v.tf {
        Value::String(p) => {
            TransferFunction::preset(p, window).map_err(|e| anyhow::anyhow!("tf: {e}"))?
        }
        t => TransferFunction::from_json(&t.to_string()).map_err(|e| anyhow::anyhow!("tf: {e}"))?,
    };
    let mode = match v.mode.as_str() {
        "mip" => RenderMode::Mip,
        "slice" => RenderMode::Slice {
            origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] / 2.0],
            normal: [0.0, 0.0, 1.0],
        },
        _ => RenderMode::Dvr,
    };
    let camera = match (&v.camera, &mode) {
        (Some(c), _) => {
            Camera::from_json(&c.to_string()).map_err(|e| anyhow::anyhow!("camera: {e}"))?
        }
        // The default views fit the volume into the image, its width as
        // well as its height (as `render`'s).
        (None, RenderMode::Slice { origin, normal }) => {
            let mut c = Camera::fit_plane(extent, *origin, *normal, v.size[0], v.size[1]);
            if let Projection::Orthographic { height } = &mut c.projection {
                *height /= v.zoom;
            }
            c
        }
        (None, _) => {
            let full = Camera::fit_image(
                extent,
                v.azimuth,
                v.elevation,
                Projection::Perspective { fov_y_deg: 35.0 },
                v.size[0],
                v.size[1],
            );
            let eye = [0, 1, 2].map(|a| full.target[a] + (full.eye[a] - full.target[a]) / v.zoom);
            Camera { eye, ..full }
        }
    };
    let mut p = RenderParams::new(v.size[0], v.size[1], camera, tf, mode);
    p.reference_step = Some(o.scene.voxel(0));
    p.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(p)
}

/// JPEG (quality 85) or PNG bytes of `img` over black.
fn encode(img: &Image, png: bool) -> Result<Vec<u8>> {
    let rgba = img.to_rgba8([0.0, 0.0, 0.0, 1.0]);
    let mut out = vec![];
    if png {
        let mut e = png::Encoder::new(&mut out, img.width, img.height);
        e.set_color(png::ColorType::Rgba);
        e.set_depth(png::BitDepth::Eight);
        e.write_header()?.write_image_data(&rgba)?;
    } else {
        let rgb: Vec<u8> = rgba.chunks(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        jpeg_encoder::Encoder::new(&mut out, 85).encode(
            &rgb,
            img.width as u16,
            img.height as u16,
            jpeg_encoder::ColorType::Rgb,
        )?;
    }
    Ok(out)
}

fn send_json(ws: &mut WebSocket<TcpStream>, v: Value) -> Result<()> {
    ws.send(Message::Text(v.to_string().into()))?;
    Ok(())
}

/// One client's session: views in, frames out.
fn session(ws: &mut WebSocket<TcpStream>, site: &RenderSite, caches: &Caches) -> Result<()> {
    let mut view = View::default();
    let mut open_store: Option<Open> = None;
    // The view being drawn: its parameters and level-of-detail budget.
    let mut drawing: Option<(RenderParams, LodBudget, u64)> = None;
    // A new view is first drawn as a preview, as the viewer draws it
    // (`frames::preview`), since when.
    let mut previewing: Option<Instant> = None;
    let min_interval = Duration::from_secs_f64(1.0 / site.max_fps.max(0.1));
    let mut last_sent = Instant::now() - min_interval;
    loop {
        // Waiting for a view: block a while; drawing: just look.
        let wait = if drawing.is_some() { 1 } else { 250 };
        ws.get_ref()
            .set_read_timeout(Some(Duration::from_millis(wait)))?;
        let mut changed = false;
        loop {
            match ws.read() {
                Ok(Message::Text(t)) => {
                    let Ok(Value::Object(mut m)) = serde_json::from_str(t.as_str()) else {
                        send_json(ws, json!({"error": "expected a JSON object"}))?;
                        continue;
                    };
                    let report = m.remove("report");
                    if let Some(r) = &report {
                        eprintln!(
                            "render client reports: {}",
                            crate::serve::loggable(r.as_str().unwrap_or(&r.to_string()))
                        );
                    }
                    if m.is_empty() {
                        if report.is_none() {
                            // Every message is answered: an empty one too.
                            send_json(
                                ws,
                                json!({"error": "an empty message: expected fields of the view (store, mode, tf, window, size, azimuth, elevation, zoom, camera) or report"}),
                            )?;
                        }
                        continue;
                    }
                    match view.apply(&m) {
                        Ok(v) => {
                            changed |= v != view;
                            view = v;
                        }
                        Err(e) => send_json(ws, json!({"error": format!("{e:#}")}))?,
                    }
                    // More messages may be queued: take them all first.
                    ws.get_ref()
                        .set_read_timeout(Some(Duration::from_millis(1)))?;
                }
                Ok(Message::Close(_)) => return Ok(()),
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    break
                }
                Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                    return Ok(())
                }
                Err(e) => return Err(e.into()),
            }
        }
        if changed {
            drawing = None;
            let Some(name) = view.store.clone() else {
                send_json(ws, json!({"error": "store: name the store to show"}))?;
                continue;
            };
            if open_store.as_ref().map(|o| o.name.as_str()) != Some(name.as_str()) {
                open_store = None;
                match open(site, caches, &name) {
                    Ok(o) => open_store = Some(o),
                    Err(e) => {
                        send_json(ws, json!({"error": format!("{e:#}")}))?;
                        continue;
                    }
                }
            }
            let o = open_store.as_ref().expect("opened above");
            match params(o, &view) {
                Ok(p) => {
                    let budget = LodBudget::new(0.0, o.scene.levels.len(), false);
                    drawing = Some((p, budget, 0));
                    previewing = Some(Instant::now());
                }
                Err(e) => send_json(ws, json!({"error": format!("{e:#}")}))?,
            }
        }
        let (Some((p, budget, frames)), Some(o)) = (drawing.as_mut(), open_store.as_mut()) else {
            continue;
        };
        // At most max-fps frames a second.
        let since = last_sent.elapsed();
        if since < min_interval {
            std::thread::sleep(min_interval - since);
        }
        let t = Instant::now();
        let lod = budget.apply(Lod::Auto { bias: 0.0 }, o.scene.levels.len());
        // The preview: sent while it is incomplete (most of the view still
        // loading), given up for full frames once it is complete, nothing
        // more is coming, or after PREVIEW_FOR. The page scales it up.
        let preview = previewing.and_then(|since| {
            brickyard_run::frames::preview(&o.backend, p, lod).map(|pp| (since, pp))
        });
        if previewing.is_some() && preview.is_none() {
            previewing = None;
        }
        if let Some((since, (pp, pl))) = preview {
            let f = o.backend.frame(&mut o.s, &o.scene, &pp, pl)?;
            let completeness = f.stats.completeness();
            if brickyard_run::frames::preview_over(&o.s, &f, since) {
                previewing = None;
            }
            if completeness < 1.0 {
                *frames += 1;
                let bytes = encode(&f.image, false)?;
                send_json(
                    ws,
                    json!({"frame": *frames, "completeness": completeness, "complete": false,
                        "final": false, "preview": true, "format": "jpeg", "width": pp.width,
                        "height": pp.height, "lod_bias": budget.bias,
                        "ms": t.elapsed().as_secs_f64() * 1e3, "bytes": bytes.len()}),
                )?;
                ws.send(Message::Binary(bytes.into()))?;
                last_sent = Instant::now();
                continue;
            }
        }
        let f = o.backend.frame(&mut o.s, &o.scene, p, lod)?;
        *frames += 1;
        let sig = brickyard_run::frames::signals(&o.s, &f);
        let decision = budget.update(&sig);
        let done = matches!(decision, Decision::Stop(_));
        let completeness = f.stats.completeness();
        let bytes = encode(&f.image, done)?;
        send_json(
            ws,
            json!({"frame": *frames, "completeness": completeness, "complete": done && completeness >= 1.0,
                "final": done, "format": if done { "png" } else { "jpeg" }, "width": p.width, "height": p.height,
                "lod_bias": budget.bias, "ms": t.elapsed().as_secs_f64() * 1e3, "bytes": bytes.len()}),
        )?;
        ws.send(Message::Binary(bytes.into()))?;
        last_sent = Instant::now();
        if done {
            drawing = None;
        }
    }
}
