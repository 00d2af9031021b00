//! The page's side (`wasm32` only): [`Viewer`], exported through
//! `wasm-bindgen`, over a store URL and a canvas; reads go through the
//! browser's `fetch()` with `Range` headers, loads run on the page's event
//! loop, frames are drawn when the page asks (each animation frame) and
//! put on the canvas.

use crate::session::{FrameOut, Spawn, WebSession};
use crate::source::{Fetch, LocalFuture, Range, WebSource};
use crate::view::ViewState;
use brickyard_cache::vm::VmConfig;
use std::cell::RefCell;
use std::rc::Rc;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::JsFuture;

/// `fetch()` below a base URL.
struct HttpFetch {
    base: String,
}

fn js_err(e: JsValue) -> String {
    e.as_string()
        .or_else(|| js_sys::JSON::stringify(&e).ok().and_then(|s| s.as_string()))
        .unwrap_or_else(|| format!("{e:?}"))
}

impl Fetch for HttpFetch {
    fn get(&self, path: &str, range: Range) -> LocalFuture<Result<Option<Vec<u8>>, String>> {
        let url = format!("{}/{}", self.base.trim_end_matches('/'), path);
        Box::pin(async move {
            // A request that stalls (a lost connection) is abandoned and
            // tried again, twice; then the brick fails.
            let mut last = String::new();
            for _ in 0..3 {
                match get_once(&url, range).await {
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

/// One `GET`; errors say whether trying again may help.
async fn get_once(url: &str, range: Range) -> Result<Option<Vec<u8>>, (String, bool)> {
    let fatal = |e: JsValue| (js_err(e), false);
    let opts = web_sys::RequestInit::new();
    opts.set_method("GET");
    // The answer's head must come within 4 s and its body within 30 s,
    // else the request is abandoned (and tried again): a request that
    // stalled on loopback was seen now and then in headless Chromium.
    let ctl = web_sys::AbortController::new().map_err(fatal)?;
    opts.set_signal(Some(&ctl.signal()));
    if range != Range::All {
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
    let resp: web_sys::Response = resp
        .map_err(|e| (format!("{url}: {}", js_err(e)), true))?
        .dyn_into()
        .map_err(fatal)?;
    match resp.status() {
        404 => return Ok(None),
        200 | 206 => {}
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
    // A server that ignores ranges answers 200 with the whole file.
    Ok(Some(match (resp.status(), range) {
        (200, Range::Span { start, len }) => {
            let e = (start + len) as usize;
            bytes
                .get(start as usize..e)
                .ok_or((format!("{url}: shorter than the range asked for"), false))?
                .to_vec()
        }
        (200, Range::Suffix(n)) => bytes[bytes.len().saturating_sub(n as usize)..].to_vec(),
        _ => bytes,
    }))
}

struct Inner {
    session: WebSession,
    state: ViewState,
    /// The default data window (the channel's `omero` window, else the
    /// data type's range).
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
    /// When the last frame was drawn (ms).
    drawn_at: f64,
}

fn now() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(0.0, |p| p.now())
}

/// The web viewer: one store, one canvas.
#[wasm_bindgen]
pub struct Viewer {
    inner: Rc<RefCell<Inner>>,
}

#[wasm_bindgen]
impl Viewer {
    /// Open the OME-Zarr store at `url` and draw into `canvas`, with the
    /// view of `query` (the page's `#…`); `pool_mib` is the brick pool.
    pub async fn open(
        url: String,
        canvas: web_sys::HtmlCanvasElement,
        query: String,
        pool_mib: u32,
    ) -> Result<Viewer, JsValue> {
        console_error_panic_hook();
        let started = now();
        let state = ViewState::from_query(&query).map_err(|e| JsValue::from_str(&e))?;
        let fetch: Rc<dyn Fetch> = Rc::new(HttpFetch { base: url.clone() });
        let src = WebSource::open(fetch, 32, 1, 32 << 20)
            .await
            .map_err(|e| JsValue::from_str(&format!("{url}: {e}")))?;
        if state.channel >= src.geometry.channels {
            return Err(JsValue::from_str(&format!(
                "channel: the store has {} channels, found {}",
                src.geometry.channels, state.channel
            )));
        }
        let window = default_window(&src, state.channel);
        let cfg = VmConfig {
            brick: [32; 3],
            pool_bytes: pool_mib as u64 * (1 << 20),
            request_cap: 256,
            upload_bytes_per_frame: 64 << 20,
            ..Default::default()
        };
        let spawn: Spawn = Rc::new(wasm_bindgen_futures::spawn_local);
        let mut session =
            WebSession::new(Rc::new(src), cfg, spawn, 32).map_err(|e| JsValue::from_str(&e))?;
        session.scene.channel = state.channel;
        let ctx = canvas
            .get_context("2d")?
            .ok_or("the canvas has no 2D context")?
            .dyn_into::<web_sys::CanvasRenderingContext2d>()?;
        Ok(Viewer {
            inner: Rc::new(RefCell::new(Inner {
                session,
                state,
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
                drawn_at: 0.0,
            })),
        })
    }

    /// Draw one frame (only what is not settled yet) and put it on the
    /// canvas; returns the status as JSON.
    pub fn frame(&self) -> Result<String, JsValue> {
        let mut g = self.inner.borrow_mut();
        let inner = &mut *g;
        let t = now();
        let (p, lod) = inner
            .state
            .params(&inner.session.scene, inner.window)
            .map_err(|e| JsValue::from_str(&e))?;
        // Draw when the view changed, or when enough bricks arrived to be
        // worth a frame: a frame holds the page's only thread, and loads
        // (decoding included) move on between frames.
        let news = inner.session.news();
        let (queued, in_flight) = inner.session.loads.pending();
        let idle = queued + in_flight == 0;
        let waited = t - inner.drawn_at >= 250.0;
        let draw = inner.frames == 0
            || inner.dirty()
            || (news > 0 && (news >= 64 || idle || waited))
            || (!inner.last.complete && idle && waited);
        if draw {
            inner.drawn_at = t;
            inner.drawn_state = Some(inner.state.clone());
            inner.last = inner.session.frame_cpu(&p, lod);
            inner.frames += 1;
            let img = inner.session.image();
            if img.width > 0 {
                if inner.canvas.width() != img.width || inner.canvas.height() != img.height {
                    inner.canvas.set_width(img.width);
                    inner.canvas.set_height(img.height);
                }
                let rgba = img.to_rgba8([0.0, 0.0, 0.0, 1.0]);
                let data = web_sys::ImageData::new_with_u8_clamped_array_and_sh(
                    wasm_bindgen::Clamped(&rgba),
                    img.width,
                    img.height,
                )?;
                inner.ctx.put_image_data(&data, 0.0, 0.0)?;
            }
            inner.frame_ms = now() - t;
        }
        let bytes = inner.session.loads.src.stats.borrow().bytes;
        let tn = now();
        if tn - inner.rate_at.0 >= 500.0 {
            inner.mib_s =
                (bytes - inner.rate_at.1) as f64 / 1048576.0 / ((tn - inner.rate_at.0) / 1000.0);
            inner.rate_at = (tn, bytes);
        }
        if inner.last.complete && inner.first_complete_ms.is_none() {
            inner.first_complete_ms = Some(tn - inner.started);
        }
        Ok(inner.status(bytes))
    }

    /// The view as the page's `#…` (without the store).
    pub fn query(&self) -> String {
        self.inner.borrow().state.to_query()
    }

    /// Set the view from a `#…` query; a bad value is an error naming
    /// its key, and the view stays as it was.
    pub fn set_query(&self, q: &str) -> Result<(), JsValue> {
        let s = ViewState::from_query(q).map_err(|e| JsValue::from_str(&e))?;
        let mut g = self.inner.borrow_mut();
        if s.channel >= g.session.vm.channels() {
            return Err(JsValue::from_str(&format!(
                "channel: the store has {} channels, found {}",
                g.session.vm.channels(),
                s.channel
            )));
        }
        if s.channel != g.state.channel {
            g.session.scene.channel = s.channel;
            g.window = default_window(&g.session.loads.src, s.channel);
        }
        g.state = s;
        Ok(())
    }

    /// Turn the camera by `daz`, `del` degrees.
    pub fn orbit(&self, daz: f64, del: f64) {
        let mut g = self.inner.borrow_mut();
        g.state.azimuth = ((g.state.azimuth + daz) % 360.0 * 1000.0).round() / 1000.0;
        g.state.elevation =
            ((g.state.elevation + del).clamp(-89.0, 89.0) * 1000.0).round() / 1000.0;
    }

    /// Move closer (`f` > 1) or away.
    pub fn zoom(&self, f: f64) {
        let mut g = self.inner.borrow_mut();
        g.state.zoom = ((g.state.zoom * f).clamp(0.2, 20.0) * 1000.0).round() / 1000.0;
    }

    /// The last image as straight 8-bit RGBA over black (what the canvas
    /// shows), for checks.
    pub fn pixels(&self) -> Vec<u8> {
        self.inner
            .borrow()
            .session
            .image()
            .to_rgba8([0.0, 0.0, 0.0, 1.0])
    }

    /// A histogram (256 bins over the default window) of the resident
    /// voxels of the shown channel: what the transfer-function editor
    /// draws under its window.
    pub fn histogram(&self) -> Vec<u32> {
        let g = self.inner.borrow();
        histogram(&g.session, g.window)
    }

    /// The store: levels, channels, data type and default window, as JSON.
    pub fn info(&self) -> String {
        let g = self.inner.borrow();
        let src = &g.session.loads.src;
        serde_json::json!({
            "levels": src.geometry.levels,
            "channels": src.meta.channels.iter().map(|c| &c.label).collect::<Vec<_>>(),
            "n_channels": src.geometry.channels,
            "dtype": format!("{:?}", src.geometry.dtype),
            "spacing": src.meta.spacing,
            "window": g.window,
            "pool_slots": g.session.vm.pool_slots(),
        })
        .to_string()
    }
}

impl Inner {
    /// Whether the view changed since the last frame drawn.
    fn dirty(&self) -> bool {
        self.drawn_state.as_ref() != Some(&self.state)
    }

    fn status(&self, bytes: u64) -> String {
        let l = &self.last;
        serde_json::json!({
            "ready": self.session.ready(),
            "complete": l.complete,
            "completeness": l.stats.completeness(),
            "bias": l.bias,
            "resident": self.session.vm.resident_bricks(),
            "pool_slots": self.session.vm.pool_slots(),
            "loaded": self.session.loads.loaded(),
            "queued": l.queued,
            "in_flight": l.in_flight,
            "failed": self.session.failures.len(),
            "last_failure": self.session.failures.last().map(|(k, e)| format!("{k:?}: {e}")),
            "bytes": bytes,
            "mib_s": self.mib_s,
            "frame_ms": self.frame_ms,
            "frames": self.frames,
            "first_complete_ms": self.first_complete_ms,
            "query": self.state.to_query(),
        })
        .to_string()
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
