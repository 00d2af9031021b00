//! The page's side (`wasm32` only): [`Viewer`], exported through
//! `wasm-bindgen`, over a store URL and a canvas; reads go through the
//! browser's `fetch()` with `Range` headers, loads run on the page's event
//! loop, frames are drawn when the page asks (each animation frame) and
//! put on the canvas.

use crate::session::{FrameOut, Spawn, WebSession};
use crate::source::{
    brick_name, cut, Fetch, Got, LocalFuture, Range, WebSource, STORE_CHANGED, UNREACHABLE,
};
use crate::view::{Backend, PoolShare, ViewState};
use brickyard_cache::vm::VmConfig;
use std::cell::RefCell;
use std::rc::Rc;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::JsFuture;

/// `fetch()` below a base URL.
struct HttpFetch {
    base: String,
    /// A bearer token for stores behind one (`brickyard serve --token`).
    token: Option<String>,
}

/// A JavaScript error as words for people: its message (a `TypeError` of
/// `fetch()`, which says nothing more, as what it means), never `{}`.
pub fn js_err(e: JsValue) -> String {
    if let Some(s) = e.as_string() {
        return s;
    }
    let field = |k: &str| {
        js_sys::Reflect::get(&e, &JsValue::from_str(k))
            .ok()
            .and_then(|v| v.as_string())
            .unwrap_or_default()
    };
    let (name, message) = (field("name"), field("message"));
    match name.as_str() {
        // (`fetch()` rejects with a TypeError, "Failed to fetch", both for
        // a server not there and for a response CORS withholds.)
        "TypeError" => return UNREACHABLE.into(),
        "AbortError" => return "no answer in time (the request was abandoned)".into(),
        _ => {}
    }
    if !message.is_empty() {
        return if name.is_empty() {
            message
        } else {
            format!("{name}: {message}")
        };
    }
    js_sys::JSON::stringify(&e)
        .ok()
        .and_then(|s| s.as_string())
        .filter(|s| s != "{}" && !s.is_empty())
        .or_else(|| {
            let s = String::from(js_sys::Object::from(e.clone()).to_string());
            (!s.is_empty()).then_some(s)
        })
        .unwrap_or_else(|| "an unknown error".into())
}

impl Fetch for HttpFetch {
    fn get(&self, path: &str, range: Range) -> LocalFuture<Result<Option<Vec<u8>>, String>> {
        let f = self.get_tagged(path, range, None);
        let path = path.to_string();
        Box::pin(async move {
            let g = f.await?;
            match g.bytes {
                Some(b) if g.whole => Ok(Some(
                    cut(&b, range).map_err(|e| format!("{path}: {e}"))?.to_vec(),
                )),
                b => Ok(b),
            }
        })
    }

    fn get_tagged(
        &self,
        path: &str,
        range: Range,
        if_match: Option<&str>,
    ) -> LocalFuture<Result<Got, String>> {
        let url = format!("{}/{}", self.base.trim_end_matches('/'), path);
        let token = self.token.clone();
        let if_match = if_match.map(str::to_string);
        Box::pin(async move {
            // A request that stalls (a lost connection) is abandoned and
            // tried again, twice; then the brick fails.
            let mut last = String::new();
            for _ in 0..3 {
                match get_once(&url, range, token.as_deref(), if_match.as_deref()).await {
                    Ok(r) => return Ok(r),
                    Err((e, retry)) => {
                        if !retry {
                            return Err(e);
                        }
                        last = e;
                    }
                }
            }
            Err(last)
        })
    }
}

/// One `GET` (with `If-Match: if_match` where given); errors say whether
/// trying again may help.
async fn get_once(
    url: &str,
    range: Range,
    token: Option<&str>,
    if_match: Option<&str>,
) -> Result<Got, (String, bool)> {
    let fatal = |e: JsValue| (js_err(e), false);
    let opts = web_sys::RequestInit::new();
    opts.set_method("GET");
    // The answer's head must come within 4 s and its body within 30 s,
    // else the request is abandoned (and tried again): a request that
    // stalled on loopback was seen now and then in headless Chromium.
    let ctl = web_sys::AbortController::new().map_err(fatal)?;
    opts.set_signal(Some(&ctl.signal()));
    if range != Range::All || if_match.is_some() {
        // Byte ranges bypass the HTTP cache: Chromium's answers to ranges
        // of a partly cached object came back empty (its sparse entries);
        // bricks have caches of their own.
        opts.set_cache(web_sys::RequestCache::NoStore);
    }
    // Each range gets a URL of its own: Chromium lets one request per URL
    // through its HTTP cache at a time and holds the others up to 20 s
    // (its cache lock), which parallel reads of one shard would hit.
    let addr = match range {
        Range::All => url.to_string(),
        Range::Span { start, len } => format!(
            "{url}{}bytes={start}-{len}",
            if url.contains('?') { '&' } else { '?' }
        ),
        Range::Suffix(n) => format!(
            "{url}{}bytes=-{n}",
            if url.contains('?') { '&' } else { '?' }
        ),
    };
    let req = web_sys::Request::new_with_str_and_init(&addr, &opts).map_err(fatal)?;
    let header = match range {
        Range::All => None,
        Range::Span { start, len } => Some(format!("bytes={}-{}", start, start + len - 1)),
        Range::Suffix(n) => Some(format!("bytes=-{n}")),
    };
    if let Some(h) = &header {
        req.headers().set("Range", h).map_err(fatal)?;
    }
    if let Some(t) = token {
        req.headers()
            .set("Authorization", &format!("Bearer {t}"))
            .map_err(fatal)?;
    }
    if let Some(t) = if_match {
        req.headers().set("If-Match", t).map_err(fatal)?;
    }
    let window = web_sys::window().ok_or(("no window".to_string(), false))?;
    let abort_after = |ms: i32| -> Result<i32, (String, bool)> {
        let c = ctl.clone();
        let cb = Closure::once_into_js(move || c.abort());
        window
            .set_timeout_with_callback_and_timeout_and_arguments_0(cb.unchecked_ref(), ms)
            .map_err(fatal)
    };
    let timer = abort_after(4_000)?;
    let resp = JsFuture::from(window.fetch_with_request(&req)).await;
    window.clear_timeout_with_handle(timer);
    // (A server not there is not asked again at once: the source stops
    // reading until its probe finds the server back, `WebSource::probe`.)
    let resp: web_sys::Response = resp
        .map_err(|e| {
            let e = js_err(e);
            let again = !e.contains(UNREACHABLE);
            (format!("{url}: {e}"), again)
        })?
        .dyn_into()
        .map_err(fatal)?;
    match resp.status() {
        404 => {
            return Ok(Got {
                bytes: None,
                etag: None,
                whole: false,
            })
        }
        200 | 206 => {}
        401 if token.is_some() => {
            return Err((
                format!(
                    "{url}: HTTP 401: the server refused the token given (token=… in the page's \
                     URL): check it"
                ),
                false,
            ))
        }
        401 => {
            return Err((
                format!("{url}: HTTP 401: the store needs a token (token=… in the page's URL)"),
                false,
            ))
        }
        412 => return Err((format!("{url}: HTTP 412: {STORE_CHANGED}"), false)),
        s @ (500..=599 | 408 | 429) => {
            return Err((format!("{url}: HTTP {s} {}", resp.status_text()), true))
        }
        s => return Err((format!("{url}: HTTP {s} {}", resp.status_text()), false)),
    }
    let timer = abort_after(30_000)?;
    let buf = JsFuture::from(resp.array_buffer().map_err(fatal)?).await;
    window.clear_timeout_with_handle(timer);
    let buf = buf.map_err(|e| (format!("{url}: {}", js_err(e)), true))?;
    let bytes = js_sys::Uint8Array::new(&buf).to_vec();
    let etag = resp.headers().get("ETag").ok().flatten();
    // A server that ignores ranges answers 200 with the whole file: it
    // goes back whole, for the source to cut, count as downloaded, and
    // keep (`WebSource::get`), not to download it again per range.
    let whole = resp.status() == 200 && range != Range::All;
    Ok(Got {
        bytes: Some(bytes),
        etag,
        whole,
    })
}

/// The device path: WebGPU's device, the page tables and pool on it, and
/// the renderer (updates decided on the host, as `--gpu-update host`).
struct DeviceDraw {
    gpu: brickyard_gpu::Gpu,
    dvm: brickyard_gpu::vm::DeviceVm,
    renderer: brickyard_render::gpu::GpuRenderer,
}

struct Inner {
    session: WebSession,
    device: Option<DeviceDraw>,
    /// The device's last image (the CPU's is the session's).
    device_image: Option<brickyard_render::Image>,
    /// The channel and default data window the scene is set up for.
    channel: usize,
    window: [f64; 2],
    ctx: web_sys::CanvasRenderingContext2d,
    canvas: web_sys::HtmlCanvasElement,
    last: FrameOut,
    frames: u64,
    frame_ms: f64,
    /// (time in ms, bytes fetched) at the last throughput reading, and the
    /// rate then.
    rate_at: (f64, u64),
    mib_s: f64,
    started: f64,
    first_complete_ms: Option<f64>,
    /// The view of the last frame drawn.
    drawn_state: Option<ViewState>,
    /// The label image's bounding boxes by label, once fetched (`Some(None)`:
    /// it has none to use).
    label_boxes: Option<Option<std::collections::HashMap<u64, [u64; 6]>>>,
    /// When the last frame was drawn (ms).
    drawn_at: f64,
    /// Why the device is not used, when it was asked for.
    device_note: Option<String>,
    /// The last frame was drawn on the device.
    on_device: bool,
    /// `labels=NAME`: the label image laid over the slice.
    labels: Option<LabelLayer>,
    /// The view of the last frame drawn, at the canvas's size (the
    /// readout's).
    view: Option<crate::view::View>,
    /// Milliseconds the last full-size redraw of a changed 3D view took
    /// (0: none yet): a moving view is drawn smaller when that is too slow
    /// (`budget::moving_scale`).
    full_ms: f64,
    /// The fraction of the canvas's size per axis the last frame was drawn
    /// at (1: full size), and a canvas to draw such frames into before
    /// they are scaled onto the page's.
    drawn_scale: f64,
    /// The last frame was drawn as a moving view's (within
    /// [`MOVING_FOR_MS`] of a camera move).
    drawn_moving: bool,
    /// The fraction of the size the last frame while moving was drawn at
    /// (1: full size, or none yet): `budget::moving_scale`'s `last`.
    moving_last: f64,
    /// Milliseconds and tiles of the frames on the CPU at rest, older ones
    /// halved at each new one: their ratio is what a tile takes, and a
    /// frame at rest is drawn in parts of about [`PART_MS`] each. (A ratio
    /// of sums: calls of many tiles weigh more than the few-tile ones,
    /// whose fixed cost per call would make the parts ever smaller.)
    tile_cost: (f64, f64),
    /// The frame being drawn (in one part or several): its milliseconds
    /// so far, its parts, and whether it redraws a changed 3D view at full
    /// size (then it sets `full_ms`). The last finished frame's parts.
    pass_ms: f64,
    pass_parts: u32,
    pass_full: bool,
    parts: u32,
    /// The parts the last full-size redraw (of `full_ms`) was drawn in.
    full_parts: u32,
    scratch: Option<(
        web_sys::HtmlCanvasElement,
        web_sys::CanvasRenderingContext2d,
    )>,
}

/// The label image of `labels=NAME`: its own session (drawn on the CPU)
/// and the image shown, the image's slice with the labels over it.
struct LabelLayer {
    session: WebSession,
    name: String,
    last: FrameOut,
    shown: Option<brickyard_render::Image>,
}

fn now() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(0.0, |p| p.now())
}

/// The web viewer: one store, one canvas. The view lives in its own cell,
/// so the page may change it while a frame is being drawn.
#[wasm_bindgen]
pub struct Viewer {
    inner: Rc<RefCell<Inner>>,
    state: Rc<RefCell<ViewState>>,
    /// When the camera last moved (`orbit`, `zoom`; ms).
    moved_at: Rc<std::cell::Cell<f64>>,
    channels: usize,
    info: String,
}

/// How long after the camera's last move (ms) the view counts as moving.
const MOVING_FOR_MS: f64 = 200.0;

/// The time a part of a frame on the CPU at rest aims at (ms): a frame that
/// takes longer is drawn over several calls, so that the page's thread is
/// never held much longer (a pointer or key waits at most about this).
const PART_MS: f64 = 40.0;

/// The most bricks × channels of a level whose statistics the page reads
/// (16 MiB of value ranges at most): finer levels of larger volumes are
/// loaded to learn what their bricks hold.
const MAX_RANGES: u64 = 1 << 21;

#[wasm_bindgen]
impl Viewer {
    /// Open the OME-Zarr store at `url` and draw into `canvas`, with the
    /// view of `query` (the page's `#…`); `pool` is the brick pool in MiB
    /// as the page's `pool=` gives it ([`crate::view::pool_bytes`]);
    /// `backend` who draws ([`Backend::parse`]: `auto`, `gpu` or `cpu`;
    /// the page passes `cpu` where the browser has no WebGPU).
    pub async fn open(
        url: String,
        canvas: web_sys::HtmlCanvasElement,
        query: String,
        pool: Option<String>,
        backend: String,
        token: Option<String>,
    ) -> Result<Viewer, JsValue> {
        console_error_panic_hook();
        let started = now();
        let backend = Backend::parse(&backend).map_err(|e| JsValue::from_str(&e))?;
        let state = ViewState::from_query(&query).map_err(|e| JsValue::from_str(&e))?;
        let fetch: Rc<dyn Fetch> = Rc::new(HttpFetch {
            base: url.clone(),
            token: token.clone().filter(|t| !t.is_empty()),
        });
        let src = WebSource::open(fetch, 32, 1, 32 << 20)
            .await
            .map_err(|e| JsValue::from_str(&format!("{url}: {e}")))?;
        if state.channel >= src.geometry.channels {
            return Err(JsValue::from_str(&format!(
                "channel: {}, found {}",
                has_channels(src.geometry.channels),
                state.channel
            )));
        }
        let window = default_window(&src, state.channel);
        // The label image takes a quarter of the pool, as in the viewer.
        let pool = crate::view::pool_bytes(pool.as_deref()).map_err(|e| JsValue::from_str(&e))?;
        let share = match state.labels {
            Some(_) => PoolShare::Image,
            None => PoolShare::All,
        };
        let cfg = VmConfig {
            brick: [32; 3],
            pool_bytes: share.of(pool),
            request_cap: 256,
            upload_bytes_per_frame: 64 << 20,
            ..Default::default()
        };
        let spawn: Spawn = Rc::new(wasm_bindgen_futures::spawn_local);
        let mut stats_problems = vec![];
        let root = url.trim_end_matches('/');
        let labels = match &state.labels {
            Some(name) => {
                let fetch: Rc<dyn Fetch> = Rc::new(HttpFetch {
                    base: format!("{}/labels/{name}", url.trim_end_matches('/')),
                    token: token.clone().filter(|t| !t.is_empty()),
                });
                let lsrc = WebSource::open(fetch, 32, 1, 8 << 20).await.map_err(|e| {
                    JsValue::from_str(&format!("labels: {root}/labels/{name}: {e}"))
                })?;
                if !lsrc.meta.labels || lsrc.geometry.channels != 1 {
                    return Err(JsValue::from_str(&format!(
                        "labels: {root}/labels/{name} is not a label image of one channel"
                    )));
                }
                // Drawn over the grid they were made on, as `render
                // --labels` takes them (else nothing would lie where it
                // belongs).
                if let Err(how) = src.meta.grid().same_as(&lsrc.meta.grid()) {
                    return Err(JsValue::from_str(&format!(
                        "labels: {root}/labels/{name}: its level 0 is {how}, the image's: label \
                         images are drawn over the grid they were made on (the same voxels, \
                         spacing, origin and unit)"
                    )));
                }
                let lcfg = VmConfig {
                    pool_bytes: PoolShare::Labels.of(pool),
                    ..cfg.clone()
                };
                let mut session =
                    WebSession::new(Rc::new(lsrc), lcfg, spawn.clone(), 16).map_err(|e| {
                        JsValue::from_str(&format!(
                            "labels: {}",
                            crate::view::pool_too_small(&e, PoolShare::Labels)
                        ))
                    })?;
                stats_problems.extend(session.read_ranges(MAX_RANGES).await);
                Some(LabelLayer {
                    session,
                    name: name.clone(),
                    last: FrameOut::default(),
                    shown: None,
                })
            }
            None => None,
        };
        let mut session = WebSession::new(Rc::new(src), cfg, spawn, 32)
            .map_err(|e| JsValue::from_str(&crate::view::pool_too_small(&e, share)))?;
        stats_problems.extend(session.read_ranges(MAX_RANGES).await);
        for p in &stats_problems {
            web_sys::console::warn_1(&JsValue::from_str(&format!("brick statistics: {p}")));
        }
        session.scene.channel = state.channel;
        let (device, device_note) = if backend != Backend::Cpu {
            match open_device(&mut session, backend).await {
                Ok(d) => (Some(d), None),
                Err(e) => (None, Some(e)),
            }
        } else {
            (None, None)
        };
        let ctx = canvas
            .get_context("2d")?
            .ok_or("the canvas has no 2D context")?
            .dyn_into::<web_sys::CanvasRenderingContext2d>()?;
        let src = &session.loads.src;
        let info = serde_json::json!({
            "levels": src.geometry.levels,
            "channels": src.meta.channels.iter().map(|c| &c.label).collect::<Vec<_>>(),
            "n_channels": src.geometry.channels,
            "dtype": format!("{:?}", src.geometry.dtype),
            "spacing": src.meta.spacing,
            "window": window,
            "pool_slots": session.vm.pool_slots(),
            "device": device.as_ref().map(|d| describe(&d.gpu)),
            "device_note": device_note,
            "label_image": src.meta.labels,
            "stats_problems": stats_problems,
        })
        .to_string();
        let channels = src.geometry.channels;
        Ok(Viewer {
            inner: Rc::new(RefCell::new(Inner {
                session,
                device,
                device_image: None,
                channel: state.channel,
                window,
                ctx,
                canvas,
                last: FrameOut::default(),
                frames: 0,
                frame_ms: 0.0,
                rate_at: (started, 0),
                mib_s: 0.0,
                started,
                first_complete_ms: None,
                drawn_state: None,
                label_boxes: None,
                drawn_at: 0.0,
                device_note,
                on_device: false,
                labels,
                view: None,
                full_ms: 0.0,
                drawn_scale: 1.0,
                drawn_moving: false,
                moving_last: 1.0,
                tile_cost: (0.0, 0.0),
                pass_ms: 0.0,
                pass_parts: 0,
                pass_full: false,
                parts: 0,
                full_parts: 0,
                scratch: None,
            })),
            state: Rc::new(RefCell::new(state)),
            moved_at: Rc::new(std::cell::Cell::new(f64::NEG_INFINITY)),
            channels,
            info,
        })
    }

    /// Draw one frame (only what is not settled yet, on the CPU) and put
    /// it on the canvas; resolves to the status as JSON. One frame at a
    /// time: await each before asking for the next.
    // The frame holds the viewer's state across the device's read-backs
    // on purpose: a second frame asked for meanwhile is refused
    // (`try_borrow_mut`), and everything else the page calls uses the view's
    // own cell or `try_borrow`.
    #[allow(clippy::await_holding_refcell_ref)]
    pub fn frame(&self) -> js_sys::Promise {
        let inner = self.inner.clone();
        let state = self.state.borrow().clone();
        let moving = now() - self.moved_at.get() < MOVING_FOR_MS;
        wasm_bindgen_futures::future_to_promise(async move {
            let mut g = inner
                .try_borrow_mut()
                .map_err(|_| JsValue::from_str("a frame is being drawn: await it first"))?;
            g.frame(state, moving).await.map(JsValue::from)
        })
    }

    /// The view as the page's `#…` (without the store).
    pub fn query(&self) -> String {
        self.state.borrow().to_query()
    }

    /// Set the view from a `#…` query; a bad value is an error naming
    /// its key, and the view stays as it was.
    pub fn set_query(&self, q: &str) -> Result<(), JsValue> {
        let s = ViewState::from_query(q).map_err(|e| JsValue::from_str(&e))?;
        if s.channel >= self.channels {
            return Err(JsValue::from_str(&format!(
                "channel: {}, found {}",
                has_channels(self.channels),
                s.channel
            )));
        }
        if s.labels != self.state.borrow().labels {
            return Err(JsValue::from_str(
                "labels: the label image is chosen when the page opens (reload it with the new labels=)",
            ));
        }
        *self.state.borrow_mut() = s;
        Ok(())
    }

    /// Turn the camera by `daz`, `del` degrees. The view counts as moving
    /// for a moment: its frames may be drawn smaller meanwhile.
    pub fn orbit(&self, daz: f64, del: f64) {
        self.moved_at.set(now());
        let mut g = self.state.borrow_mut();
        g.azimuth = ((g.azimuth + daz) % 360.0 * 1000.0).round() / 1000.0;
        g.elevation = ((g.elevation + del).clamp(-89.0, 89.0) * 1000.0).round() / 1000.0;
    }

    /// The view is being changed by a drag on a control (the transfer
    /// function's window, the LOD bias): for a moment its frames may be
    /// drawn smaller, as while the camera moves.
    pub fn moving(&self) {
        self.moved_at.set(now());
    }

    /// Move closer (`f` > 1) or away (the view moving, as with `orbit`).
    pub fn zoom(&self, f: f64) {
        self.moved_at.set(now());
        let mut g = self.state.borrow_mut();
        g.zoom = ((g.zoom * f).clamp(0.2, 20.0) * 1000.0).round() / 1000.0;
    }

    /// The last image as straight 8-bit RGBA over black (what the canvas
    /// shows), for checks; empty while a frame is being drawn.
    pub fn pixels(&self) -> Vec<u8> {
        match self.inner.try_borrow() {
            Ok(g) => g.image().to_rgba8([0.0, 0.0, 0.0, 1.0]),
            Err(_) => vec![],
        }
    }

    /// A histogram (256 bins over the default window) of the resident
    /// voxels of the shown channel: what the transfer-function editor
    /// draws under its window (empty while a frame is being drawn).
    pub fn histogram(&self) -> Vec<u32> {
        match self.inner.try_borrow() {
            Ok(g) => histogram(&g.session, g.window),
            Err(_) => vec![],
        }
    }

    /// The readout under pixel position `(x, y)` of the canvas (a slice):
    /// world point, level-0 voxel, each channel's value and the level that
    /// served it, the label there with `labels=`; JSON, empty for other
    /// modes, off the volume and while a frame is being drawn.
    pub fn probe(&self, x: f64, y: f64) -> String {
        let Ok(g) = self.inner.try_borrow() else {
            return String::new();
        };
        let Some(v) = &g.view else {
            return String::new();
        };
        let labels = g.labels.as_ref().map(|l| &l.session);
        crate::session::probe(v, &g.session, labels, x, y).map_or(String::new(), |j| j.to_string())
    }

    /// The store: levels, channels, data type, default window and the
    /// device drawing, as JSON.
    pub fn info(&self) -> String {
        self.info.clone()
    }
}

/// WebGPU's device and a mirror of the session's virtual memory on it.
async fn open_device(session: &mut WebSession, backend: Backend) -> Result<DeviceDraw, String> {
    let gpu = brickyard_gpu::Gpu::new_web()
        .await
        .map_err(|e| e.to_string())?;
    if backend == Backend::Auto && gpu.info.device_type == wgpu::DeviceType::Cpu {
        return Err(format!(
            "the browser's WebGPU adapter is a software one{}, slower here than the page's own \
             CPU renderer; backend=gpu uses it anyway",
            Some(gpu.info.name.as_str())
                .filter(|n| !n.is_empty())
                .map(|n| format!(" ({n})"))
                .unwrap_or_default()
        ));
    }
    let scope = gpu.device.push_error_scope(wgpu::ErrorFilter::Validation);
    let (dvm, _) =
        brickyard_gpu::vm::DeviceVm::new(&gpu, &mut session.vm).map_err(|e| e.to_string())?;
    let renderer = brickyard_render::gpu::GpuRenderer::new(&gpu);
    if let Some(e) = scope.pop().await {
        return Err(format!("WebGPU refused the renderer: {e}"));
    }
    Ok(DeviceDraw { gpu, dvm, renderer })
}

impl Inner {
    /// What the canvas shows: the image, with the labels over it.
    fn image(&self) -> &brickyard_render::Image {
        if let Some(img) = self.labels.as_ref().and_then(|l| l.shown.as_ref()) {
            return img;
        }
        self.drawn_image()
    }

    /// The image's last frame.
    fn drawn_image(&self) -> &brickyard_render::Image {
        match (self.on_device, &self.device_image) {
            (true, Some(i)) => i,
            _ => self.session.image(),
        }
    }

    async fn frame(&mut self, state: ViewState, moving: bool) -> Result<String, JsValue> {
        let t = now();
        let src = self.session.loads.src.clone();
        let view = state
            .params(
                &self.session.scene,
                self.window,
                &src.meta.channels,
                src.geometry.channels,
                src.meta.labels,
            )
            .map_err(|e| JsValue::from_str(&e))?;
        // A label image drawing only some labels: where they lie, from its
        // statistics (fetched once), so bricks none of them reaches are
        // crossed. Without them (none, too large, unreadable), as before.
        let only = view.params.labels && view.params.label_select.as_ref().is_some_and(|s| !s.hide);
        if only && self.label_boxes.is_none() {
            let table = src.label_boxes(32 << 20).await.unwrap_or_else(|e| {
                web_sys::console::warn_1(&JsValue::from_str(&format!(
                    "label statistics not used: {e}"
                )));
                None
            });
            self.label_boxes = Some(table);
        }
        let view = match self.label_boxes.as_ref().and_then(|t| t.as_ref()) {
            Some(t) if only => view.with_label_boxes(t, src.geometry.levels[0]),
            _ => view,
        };
        if view.channel != self.channel {
            self.channel = view.channel;
            self.session.scene.channel = view.channel;
            if state.window.is_none() {
                self.window = default_window(&src, view.channel);
            }
            return Box::pin(self.frame(state, moving)).await;
        }
        self.session.octree_depth = view.octree_depth;
        self.view = Some(view.clone());
        let (full_w, full_h) = (view.params.width, view.params.height);
        // While the camera moves, a 3D view whose full-size redraws are
        // slow is drawn smaller and scaled up, as in the viewer; at rest
        // it is drawn at full size again.
        let three_d = !matches!(view.params.mode, brickyard_render::RenderMode::Slice { .. });
        let scale = if moving && three_d {
            brickyard_render::budget::moving_scale(self.full_ms, self.moving_last)
        } else {
            1.0
        };
        let mut view = view;
        [view.params.width, view.params.height] =
            brickyard_render::budget::scaled_size([full_w, full_h], scale);
        let label_view = state.label_view(&view);
        let (p, lod) = (view.params, view.lod);
        // Draw when the view changed, or when enough bricks arrived to be
        // worth a frame: a frame holds the page's only thread, and loads
        // (decoding included) move on between frames.
        // Failed bricks are asked for again now and then (a server back
        // up), as in the native viewer; and while bricks are loading or
        // failing, the store is checked for a change on the server.
        let mut retried = self.session.retry_failed(t);
        self.session.check_store(t);
        if let Some(l) = &mut self.labels {
            retried |= l.session.retry_failed(t);
            l.session.check_store(t);
        }
        if retried {
            self.drawn_state = None;
        }
        let news = self.session.news();
        let (queued, in_flight) = self.session.loads.pending();
        let idle = queued + in_flight == 0;
        let waited = t - self.drawn_at >= 250.0;
        let dirty = self.drawn_state.as_ref() != Some(&state) || self.drawn_scale != scale;
        // (A frame begun in parts goes on.)
        let in_parts = self.session.in_parts();
        let draw = self.frames == 0
            || dirty
            || in_parts
            || (news > 0 && (news >= 64 || idle || waited))
            || (!self.last.complete && idle && waited);
        let mut earlier_parts_ms = 0.0;
        if draw {
            if dirty || !in_parts {
                // A new frame (a changed view drops one begun).
                self.pass_ms = 0.0;
                self.pass_parts = 0;
                // A changed 3D view at full size is redrawn whole: what a
                // moving view would cost at full size. (Not the page's
                // first frame: it also pays for setting up, and took 10-20
                // times a later redraw.)
                self.pass_full = dirty && scale == 1.0 && three_d && self.frames > 0;
            }
            if moving && three_d {
                self.moving_last = scale;
            }
            self.drawn_at = t;
            self.drawn_state = Some(state.clone());
            self.drawn_scale = scale;
            self.drawn_moving = moving && three_d;
            let device = self.device.as_mut();
            self.on_device = device.is_some();
            self.last = match device {
                // At rest, a frame slower than a part's time is drawn in
                // parts (a moving view's frames are drawn whole, small).
                None => {
                    let (ms, tiles) = self.tile_cost;
                    let max_tiles = (!moving && self.frames > 0 && ms > 0.0 && tiles > 0.0)
                        .then(|| ((PART_MS * tiles / ms) as usize).max(1));
                    let out = self.session.frame_cpu_part(&p, lod, max_tiles);
                    if out.tiles_drawn > 0 && self.frames > 0 && !moving {
                        self.tile_cost =
                            (0.5 * ms + (now() - t), 0.5 * tiles + out.tiles_drawn as f64);
                    }
                    out
                }
                Some(d) => match self.session.prepare(&p, lod) {
                    Err(out) => *out,
                    Ok((drawn, failed)) => {
                        self.session.vm.begin_frame();
                        let f = d
                            .renderer
                            .render_async(
                                &d.gpu,
                                &d.dvm,
                                &self.session.vm,
                                &self.session.scene,
                                &p,
                                drawn,
                            )
                            .await
                            .map_err(|e| JsValue::from_str(&e.to_string()))?;
                        let out = self.session.finish(f.stats, [&f.requests], failed);
                        d.dvm.sync(&d.gpu, &mut self.session.vm);
                        self.device_image = Some(f.image);
                        out
                    }
                },
            };
            let ms = now() - t;
            earlier_parts_ms = self.pass_ms;
            self.pass_ms += ms;
            self.pass_parts += 1;
            if !self.session.in_parts() {
                self.frames += 1;
                self.parts = self.pass_parts;
                if self.pass_full {
                    self.full_ms = self.pass_ms;
                    self.full_parts = self.pass_parts;
                }
            }
        }
        // The labels: drawn with the image, and when their bricks come.
        // (A frame in parts is shown once its last part is drawn.)
        let whole = !self.session.in_parts();
        let mut shown = draw && whole;
        if let (Some(l), Some(lv)) = (&mut self.labels, &label_view) {
            let news = l.session.news();
            let (q, f) = l.session.loads.pending();
            if draw || news > 0 || (!l.last.complete && q + f == 0) {
                l.last = l.session.frame_cpu(&lv.params, lv.lod);
                shown = whole;
            }
        }
        if shown {
            let lay = match (&self.labels, &label_view) {
                (Some(l), Some(_)) => {
                    let mut img = self.drawn_image().clone();
                    img.lay_labels_over(l.session.image(), state.label_opacity as f32)
                        .ok()
                        .map(|_| img)
                }
                _ => None,
            };
            if let Some(l) = &mut self.labels {
                l.shown = lay;
            }
            let img = self.image();
            if img.width > 0 && img.width == p.width {
                let (w, h) = (img.width, img.height);
                let rgba = img.to_rgba8([0.0, 0.0, 0.0, 1.0]);
                if self.canvas.width() != full_w || self.canvas.height() != full_h {
                    self.canvas.set_width(full_w);
                    self.canvas.set_height(full_h);
                }
                let data = web_sys::ImageData::new_with_u8_clamped_array_and_sh(
                    wasm_bindgen::Clamped(&rgba),
                    w,
                    h,
                )?;
                if (w, h) == (full_w, full_h) {
                    self.ctx.put_image_data(&data, 0.0, 0.0)?;
                } else {
                    // A smaller frame: through a canvas of its size,
                    // scaled onto the page's (smoothed).
                    let (sc, sctx) = match self.scratch.take() {
                        Some(x) => x,
                        None => {
                            let c = web_sys::window()
                                .and_then(|w| w.document())
                                .ok_or("no document")?
                                .create_element("canvas")?
                                .dyn_into::<web_sys::HtmlCanvasElement>()?;
                            let x = c
                                .get_context("2d")?
                                .ok_or("no 2D context")?
                                .dyn_into::<web_sys::CanvasRenderingContext2d>()?;
                            (c, x)
                        }
                    };
                    if sc.width() != w || sc.height() != h {
                        sc.set_width(w);
                        sc.set_height(h);
                    }
                    sctx.put_image_data(&data, 0.0, 0.0)?;
                    self.ctx.draw_image_with_html_canvas_element_and_dw_and_dh(
                        &sc,
                        0.0,
                        0.0,
                        full_w as f64,
                        full_h as f64,
                    )?;
                    self.scratch = Some((sc, sctx));
                }
            }
            // (A frame in parts: all its parts.)
            self.frame_ms = now() - t + earlier_parts_ms;
        }
        let bytes = self.session.loads.src.stats.borrow().bytes;
        let tn = now();
        if tn - self.rate_at.0 >= 500.0 {
            self.mib_s =
                (bytes - self.rate_at.1) as f64 / 1048576.0 / ((tn - self.rate_at.0) / 1000.0);
            self.rate_at = (tn, bytes);
        }
        if self.complete() && self.first_complete_ms.is_none() {
            self.first_complete_ms = Some(tn - self.started);
        }
        Ok(self.status(bytes, &state))
    }

    /// The image's view and the labels over it are complete, at full
    /// size (a moving view's smaller frame is not).
    fn complete(&self) -> bool {
        self.drawn_scale == 1.0
            && self.last.complete
            && self.labels.as_ref().is_none_or(|l| l.last.complete)
    }

    fn status(&self, bytes: u64, state: &ViewState) -> String {
        let l = &self.last;
        let labels = self.labels.as_ref().map(|x| {
            serde_json::json!({
                "name": x.name, "complete": x.last.complete,
                "completeness": x.last.stats.completeness(),
                "resident": x.session.vm.resident_bricks(),
                "failed": x.session.failing(),
                "last_failure": x.session.failures.last().map(|(k, e)| format!("{}: {e}", brick_name(k))),
            })
        });
        serde_json::json!({
            "ready": self.session.ready(),
            "complete": self.complete(),
            "labels": labels,
            "completeness": l.stats.completeness(),
            "bias": l.bias,
            "resident": self.session.vm.resident_bricks(),
            "pool_slots": self.session.vm.pool_slots(),
            "loaded": self.session.loads.loaded(),
            "queued": l.queued,
            "in_flight": l.in_flight,
            "failed": self.session.failing(),
            "failures": self.session.failures.len(),
            "last_failure": self.session.failures.last().map(|(k, e)| format!("{}: {e}", brick_name(k))),
            // The server did not answer (down, or CORS): nothing is asked
            // of it but a probe every 20 s, and the view is drawn from
            // what it has.
            "unreachable": self.session.unreachable()
                || self.labels.as_ref().is_some_and(|l| l.session.unreachable()),
            // Complete, but drawn from coarser data where bricks failed or
            // could not be asked for.
            "degraded": self.complete()
                && (self.session.failing() > 0
                    || self.session.unreachable()
                    || self.labels.as_ref().is_some_and(|l| {
                        l.session.failing() > 0 || l.session.unreachable()
                    })),
            // The LOD bias the view asked for (`bias=`): `bias` above it
            // is the pool's doing.
            "bias_asked": state.lod_bias,
            "store_changed": self.session.loads.src.changed()
                || self.labels.as_ref().is_some_and(|l| l.session.loads.src.changed()),
            "bytes": bytes,
            "mib_s": self.mib_s,
            "frame_ms": self.frame_ms,
            "scale": self.drawn_scale,
            "moving": self.drawn_moving,
            "full_ms": self.full_ms,
            "parts": self.parts,
            "full_parts": self.full_parts,
            "tiles_left": self.last.tiles_left,
            "frames": self.frames,
            "first_complete_ms": self.first_complete_ms,
            "query": state.to_query(),
            "device": self.device.as_ref().map(|d| describe(&d.gpu)),
            "device_note": self.device_note,
            "on_device": self.on_device,
        })
        .to_string()
    }
}

/// "the store has N channel(s)", in words.
fn has_channels(n: usize) -> String {
    match n {
        1 => "the store has 1 channel (0)".into(),
        n => format!("the store has {n} channels (0 to {})", n - 1),
    }
}

/// The WebGPU adapter for people: its name where the browser gives one,
/// and its kind ("a software adapter"), not the driver's debug fields.
fn describe(gpu: &brickyard_gpu::Gpu) -> String {
    let kind = match gpu.info.device_type {
        wgpu::DeviceType::Cpu => "a software adapter",
        wgpu::DeviceType::IntegratedGpu => "an integrated GPU",
        wgpu::DeviceType::DiscreteGpu => "a discrete GPU",
        wgpu::DeviceType::VirtualGpu => "a virtual GPU",
        wgpu::DeviceType::Other => "the browser's adapter",
    };
    match gpu.info.name.trim() {
        "" => kind.to_string(),
        n => format!("{n}, {kind}"),
    }
}

/// The channel's `omero` window, else the data type's range.
fn default_window(src: &WebSource, channel: usize) -> [f64; 2] {
    if let Some(w) = src.meta.channels.get(channel).and_then(|c| c.window) {
        return w;
    }
    use brickyard_core::DType::*;
    match src.geometry.dtype {
        U8 => [0.0, 255.0],
        I8 => [-128.0, 127.0],
        U16 => [0.0, 65535.0],
        I16 => [-32768.0, 32767.0],
        U32 => [0.0, u32::MAX as f64],
        I32 => [i32::MIN as f64, i32::MAX as f64],
        F32 | F64 => [0.0, 1.0],
    }
}

fn histogram(s: &WebSession, [lo, hi]: [f64; 2]) -> Vec<u32> {
    let mut h = vec![0u32; 256];
    let dt = s.vm.dtype();
    let k = 256.0 / (hi - lo);
    for slot in s.vm.resident_slots() {
        let v = s.vm.slot_voxels(slot);
        brickyard_core::dispatch_dtype!(dt, T => {
            let vals: &[T] = brickyard_core::cast_slice(v);
            for x in vals.iter().step_by(7) {
                use brickyard_core::Sample;
                let b = ((x.to_f64() - lo) * k).floor();
                if (0.0..256.0).contains(&b) {
                    h[b as usize] += 1;
                }
            }
        });
    }
    h
}

fn console_error_panic_hook() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        std::panic::set_hook(Box::new(|info| {
            web_sys::console::error_1(&JsValue::from_str(&format!("brickyard: {info}")));
        }));
    });
}
