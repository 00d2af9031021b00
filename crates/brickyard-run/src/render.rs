//! `brickyard render`: DVR, MIP or a slice of a store to PNG, out of core
//! through the virtual memory, frame after frame until the view is complete.

use crate::share::{Share, Split};
use anyhow::{bail, Context, Result};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, CameraFile, Projection};
use brickyard_core::TransferFunction;
use brickyard_render::budget::Stop;
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::octree::{DEFAULT_DEPTH, MAX_DEPTH, MIN_DEPTH};
use brickyard_render::params::{DebugCounts, LabelSelect, Traversal};
use brickyard_render::reference::{RenderMode, RenderParams};
use brickyard_store::import::zarr;
use brickyard_store::info::{human_bytes, inspect};
use brickyard_store::omezarr::OmeroChannel;
use brickyard_store::VolumeSource;
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Clone)]
pub struct RenderCmd {
    /// An OME-Zarr store (convert other formats first).
    store: PathBuf,
    /// dvr, mip or slice.
    #[arg(long, default_value = "dvr")]
    mode: String,
    /// Image size WxH (or N: square); given twice, the last one (a view's
    /// saved arguments, then a larger size).
    #[arg(long, default_value = "512x512", overrides_with = "size")]
    size: String,
    /// Output PNG (a turntable writes NAME-0000.png, NAME-0001.png, ...).
    #[arg(long, short, default_value = "render.png")]
    out: PathBuf,
    /// Camera JSON file (as written by `--save-camera` or the viewer); in
    /// slice mode also the plane saved with it (`slice_origin`,
    /// `slice_normal`), where --slice-* options do not place it.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// dvr, mip: the camera's angle around the volume in degrees
    /// (default 30).
    #[arg(long, allow_hyphen_values = true)]
    azimuth: Option<f64>,
    /// dvr, mip: the camera's angle above the volume in degrees (default
    /// 20).
    #[arg(long, allow_hyphen_values = true)]
    elevation: Option<f64>,
    /// dvr, mip: vertical field of view in degrees (perspective; default
    /// 35).
    #[arg(long)]
    fov: Option<f64>,
    /// dvr, mip: orthographic projection.
    #[arg(long)]
    ortho: bool,
    /// Write the camera used to this JSON file (in slice mode with the
    /// plane: --camera draws the same slice).
    #[arg(long)]
    save_camera: Option<PathBuf>,
    /// Transfer function: a preset (linear, soft, hot, viridis, coolwarm,
    /// opaque) or a JSON file; `labels` for a label image: each label in
    /// its own colour (nearest voxels, 0 clear), in a slice the plane's
    /// labels, in dvr the first label along each ray shaded by its surface
    /// (the default in these modes for label images: a store's
    /// `labels/NAME`, or one converted with --labels). Default: soft.
    #[arg(long)]
    tf: Option<String>,
    /// Slice: draw the store's label image `labels/NAME` (as `brickyard
    /// process ... label(...) --out NAME` writes it) over the slice, each
    /// label in its own colour at --label-opacity, label 0 clear. The
    /// labels are read through a pool of their own, after the image, under
    /// the same --memory.
    #[arg(long, value_name = "NAME")]
    labels: Option<String>,
    /// --labels: the labels' opacity over the image, above 0 and at most 1
    /// (default 0.5).
    #[arg(long, value_name = "A")]
    label_opacity: Option<f32>,
    /// Label images: draw only these labels (e.g. `3,17,40-45`); the others
    /// are background (clear in slices; rays go on through them in 3D).
    #[arg(long, value_name = "IDS", conflicts_with = "hide_labels")]
    only_labels: Option<String>,
    /// Label images: draw every label but these (e.g. `3,17,40-45`).
    #[arg(long, value_name = "IDS", allow_hyphen_values = true)]
    hide_labels: Option<String>,
    /// Data window LO,HI (default: the 0.5th and 99.5th percentiles of the
    /// values of the finest level of at most four million voxels).
    #[arg(long, allow_hyphen_values = true)]
    window: Option<String>,
    /// A channel to show, `C[:COLOR[:LO,HI]]` (repeat for several). In mip
    /// and slice modes the channels are added up, each windowed to LO,HI
    /// and tinted with COLOR (red, green, blue, cyan, magenta, yellow,
    /// orange, white, gray or RRGGBB hex); in dvr several channels are
    /// composited per sample, each through its own transfer function
    /// (--channel-tf, else its colour with opacity rising over its
    /// window); one channel goes through --tf. COLOR and LO,HI default to
    /// the store's `omero` metadata, then white and --window. Default: the
    /// store's active `omero` channels when it has several, else channel
    /// 0 through the transfer function.
    #[arg(long = "channel", allow_hyphen_values = true)]
    channels: Vec<String>,
    /// DVR of several channels: channel C's transfer function, `C=PRESET`
    /// (a preset as for --tf, over the channel's window) or `C=FILE` (a
    /// JSON file as for --tf); repeat for several.
    #[arg(long = "channel-tf", value_name = "C=PRESET|FILE")]
    channel_tfs: Vec<String>,
    /// DVR of several channels: channel C drawn only at pyramid levels LO
    /// to HI, `C=LO-HI` (`C=L`: level L alone; repeat for several). A
    /// step asking for a finer level reads the channel at LO, a coarser
    /// one at HI: a context channel drawn coarse costs a fraction of the
    /// bricks of one drawn in full.
    #[arg(long = "channel-levels", value_name = "C=LO-HI")]
    channel_levels: Vec<String>,
    /// A live derived channel: this processing pipeline (stages as in
    /// `brickyard process`, e.g. `gauss(1.5)|sobel`; no `label`) applied to
    /// the shown channel, each brick computed when the view asks for it, at
    /// every level (σ in voxels scaled to the level). Shown instead of the
    /// stored channel; --window is then in the derived values, and a bare
    /// `--channel C` names the channel it is computed from.
    #[arg(long)]
    derive: Option<String>,
    /// Slice: position of the plane along z as a fraction of the depth
    /// (default 0.5, or the --camera file's plane): the plane goes through
    /// the centres of the voxel layer that holds it (one layer, not a
    /// blend of two).
    #[arg(long, allow_negative_numbers = true)]
    slice_z: Option<f64>,
    /// Slice: a point of the plane in world coordinates X,Y,Z (the
    /// volume's corner at 0, voxels `spacing` apart: the store's
    /// translation is not added; as cameras are given) (instead of
    /// --slice-z; as the viewer's saved views give it). A plane between
    /// two voxel layers samples them trilinearly (a blend of both, unlike
    /// --slice-z).
    #[arg(long, allow_hyphen_values = true)]
    slice_origin: Option<String>,
    /// Slice: a point of the plane in the store's physical coordinates
    /// X,Y,Z, in its unit with its translation added (as `brickyard info`
    /// lists them and the converted file's header placed the voxels: e.g.
    /// a brain's coordinates from its NIfTI header) (instead of --slice-z
    /// and --slice-origin). Sampled trilinearly as --slice-origin is.
    #[arg(long, allow_hyphen_values = true)]
    slice_at: Option<String>,
    /// Slice: the plane's normal X,Y,Z (default 0,0,1, or the --camera
    /// file's).
    #[arg(long, allow_hyphen_values = true)]
    slice_normal: Option<String>,
    /// Render this level only (default: automatic level of detail); a pool
    /// too small for its bricks draws coarser and says so.
    #[arg(long, allow_negative_numbers = true)]
    level: Option<usize>,
    /// Automatic level of detail: shift by this many levels (negative = finer).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    lod_bias: f64,
    /// dvr, mip: samples per voxel along a ray (default 1).
    #[arg(long)]
    samples_per_voxel: Option<f64>,
    /// Memory for the whole process: the brick pool, host cache, decoded
    /// chunks and images are split out of it (default: a quarter of RAM, or
    /// of the control group's memory limit where lower, divided among the
    /// MPI ranks on this node, and within an address-space limit, ulimit
    /// -v). An explicit --memory is each rank's.
    #[arg(long)]
    memory: Option<String>,
    /// Brick-pool budget (default: a share of --memory). A pool smaller
    /// than the view's working set costs detail, not completeness: the
    /// view is drawn as fine as the pool allows, and the run says so.
    #[arg(long)]
    pool: Option<String>,
    /// Host-cache budget (default: a share of --memory).
    #[arg(long)]
    host: Option<String>,
    /// Engine brick edge (4 to 512 voxels; smaller bricks cost far more in
    /// bookkeeping than they save: a view at 2 took minutes).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u64).range(4..=512))]
    brick: u64,
    /// Bytes written into the pool per frame (default: the pool in batch
    /// renders, 64MiB with --stream).
    #[arg(long)]
    upload: Option<String>,
    /// Requests per frame (default: what the pool and host cache hold,
    /// 256 to 4096 in batch renders, 256 to 1024 with --stream).
    #[arg(long)]
    requests: Option<usize>,
    /// Draw a frame for each batch of arriving bricks, as a viewer does,
    /// instead of loading each frame's working set before drawing again.
    #[arg(long)]
    stream: bool,
    /// DVR (CPU or device): after the view is complete, accumulate N frames of
    /// samples at new positions along each ray (frame k shifted within
    /// the step by a Halton offset), blended in depth order: the image of
    /// N times the sampling rate. Each frame's time and the memory the
    /// kept samples take are printed.
    #[arg(long, value_name = "N")]
    progressive: Option<u32>,
    /// N views in one frame (2 to 16; --size is each view's): in dvr and
    /// mip, cameras --eye-separation apart along the baseline (off-axis);
    /// in slice mode, a super-slice of N slices --spacing apart, each view
    /// seeing them shifted by --parallax. Written as --multiplex says.
    #[arg(long, value_name = "N")]
    views: Option<u32>,
    /// Super-slices: pixels of shift between neighbouring views per slice
    /// away from the reference slice (Δx; default 1).
    #[arg(long, value_name = "DX", allow_negative_numbers = true)]
    parallax: Option<f64>,
    /// Super-slices: slices between the stack's slices, in voxels of
    /// level 0 (Δz; default 1).
    #[arg(long, value_name = "DZ")]
    spacing: Option<f64>,
    /// How N views are written: `tiles` (a grid, the default) or a JSON
    /// file of the display's sub-pixel filters (`{"views": N, "pattern":
    /// [[…]]}` or `{"views": N, "lens": L, "slant": S, "offset": O}`),
    /// multiplexed into one image.
    #[arg(long, value_name = "FILE|tiles")]
    multiplex: Option<String>,
    /// Stereo pair (dvr, mip): sbs (side by side, left first), tb (left
    /// above right) or anaglyph (red–cyan).
    #[arg(long)]
    stereo: Option<String>,
    /// Distance between neighbouring eyes in world units (default: a
    /// thirtieth of the distance to the target, where the views agree).
    #[arg(long, value_name = "D")]
    eye_separation: Option<f64>,
    /// Threads that read and decode bricks (1 to 256).
    #[arg(long, default_value_t = 2)]
    loader_threads: usize,
    /// Slow every brick read down by this many milliseconds (a slow disk).
    #[arg(long, default_value_t = 0)]
    read_delay_ms: u64,
    /// A safety net: stop (and write what there is) after this many
    /// frames of a view, its quarter-size request passes included (the
    /// last frame is always the full image; with --distribute image, per
    /// band). Runs end by themselves: complete at the finest detail the
    /// pool holds, or when nothing more can arrive.
    #[arg(long, default_value_t = 2000)]
    max_frames: usize,
    /// Render a turntable of N views (1 to 3600).
    #[arg(long, value_parser = parse_views)]
    turntable: Option<u32>,
    /// Print one JSON line per frame.
    #[arg(long)]
    json: bool,
    /// Print only the final frame of each view.
    #[arg(long)]
    quiet: bool,
    /// auto (a hardware GPU when there is one, else the
    /// CPU), gpu or cpu.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// On the GPU, who decides cache updates: device (its own LRU and
    /// page tables; only requests and slot numbers come back) or host (the
    /// device mirrors the host's decisions). Default: device, host with
    /// --traversal octree (the octree follows the host's virtual memory).
    #[arg(long, value_name = "device|host")]
    gpu_update: Option<crate::backend::GpuUpdate>,
    /// DVR: how rays find their bricks: page-table (the page tables at
    /// every step) or octree (the residency octree: empty and homogeneous
    /// nodes skipped, misses substituted from the levels a node has). The
    /// octree draws unshaded DVR, on the CPU or the GPU (with updates
    /// decided on the host).
    #[arg(long, default_value = "page-table", value_name = "octree|page-table")]
    traversal: String,
    /// --traversal octree: the octree's depth, 1 to 7 (default 4).
    #[arg(long, value_name = "D")]
    octree_depth: Option<u32>,
    /// DVR on the CPU: write a count per pixel in false colour instead of
    /// the image (black 0, then blue, green, yellow, white at the largest
    /// count): octree nodes visited (0 with page tables), bricks entered
    /// or ray steps; drawn once the view is complete.
    #[arg(long, value_name = "nodes|bricks|steps")]
    debug: Option<String>,
    /// Under mpirun: how the ranks share the render: image (bands of
    /// tiles handed out on demand, the default) or data (sort-last: each
    /// rank draws its k-d region of the volume, the partial images are
    /// composited in visibility order; DVR and MIP of one channel, no early
    /// ray termination). Both draw on the CPU, or with --backend gpu each
    /// rank on a device of its own (adapter rank modulo the adapters).
    #[arg(long, value_name = "image|data")]
    pub distribute: Option<String>,
    /// DVR: composite every sample of a ray (no early termination at an
    /// opacity of 0.99): the image `--distribute data` composites exactly.
    #[arg(long)]
    pub no_early_termination: bool,
    /// --distribute data: what the k-d split balances among the ranks:
    /// view (the default: the length of the view's rays in each brick,
    /// times its data weight), data (by the store's per-brick statistics, a
    /// brick the rays draw weighs 1, one they cross without drawing (DVR:
    /// hidden by the transfer function; MIP: empty or constant) 1/16) or
    /// uniform (every brick the same). Refused without --distribute data.
    #[arg(long, value_name = "view|data|uniform")]
    pub region_weights: Option<String>,
    /// Also write each image as premultiplied linear RGBA in 32-bit floats
    /// (little-endian, row-major, top row first, width × height × 4) beside
    /// its PNG, with the extension .f32: what the renderer computed, before
    /// 8-bit rounding.
    #[arg(long)]
    pub raw_f32: bool,
    /// Print nothing (a caller that takes the images, not the PNG files).
    #[arg(skip)]
    silent: bool,
    /// The images are not written (a caller that takes them in memory):
    /// `--out`'s folder need not be writable.
    #[arg(skip)]
    in_memory: bool,
    /// Set from outside (Ctrl-C): the render stops within a band of tiles
    /// of its frame with [`crate::process::Interrupted`].
    #[arg(skip)]
    stop: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

impl RenderCmd {
    /// The images stay in memory (see [`views`]): `--out` names them but
    /// is not written, so its folder is not checked (a notebook started
    /// in a read-only folder still renders).
    pub fn in_memory(mut self) -> RenderCmd {
        self.in_memory = true;
        self
    }

    /// Stop (with [`crate::process::Interrupted`]) once `stop` is set.
    pub fn with_stop(mut self, stop: std::sync::Arc<std::sync::atomic::AtomicBool>) -> RenderCmd {
        self.stop = Some(stop);
        self
    }
}

/// Flags that hold for some modes only, refused in the others (they would
/// change nothing), and flags that the camera of `--camera` replaces;
/// `--mode` itself.
fn check_mode_flags(c: &RenderCmd) -> Result<()> {
    let mode = c.mode.as_str();
    // The flags that place and shape the camera.
    let camera_flags = [
        ("azimuth", c.azimuth.is_some()),
        ("elevation", c.elevation.is_some()),
        ("fov", c.fov.is_some()),
        ("ortho", c.ortho),
        // (A turntable's camera orbits a plane that stays: seen edge on,
        // frames came out black.)
        ("turntable", c.turntable.is_some()),
    ];
    match mode {
        "dvr" | "mip" => {
            for (flag, given) in [
                ("slice-z", c.slice_z.is_some()),
                ("slice-origin", c.slice_origin.is_some()),
                ("slice-at", c.slice_at.is_some()),
                ("slice-normal", c.slice_normal.is_some()),
            ] {
                if given {
                    bail!(
                        "{flag}: applies to --mode slice only (it places the slice's plane); \
                         --mode {mode} draws the whole volume"
                    );
                }
            }
        }
        "slice" => {
            for (flag, given) in camera_flags {
                if given {
                    bail!(
                        "{flag}: applies to --mode dvr and mip only; a slice is seen face on \
                         (move its plane with --slice-z, --slice-origin or --slice-normal, or \
                         give the camera with --camera)"
                    );
                }
            }
            if c.samples_per_voxel.is_some() {
                bail!(
                    "samples-per-voxel: applies to --mode dvr and mip only (their rays take \
                     samples; a slice takes one per pixel)"
                );
            }
            if c.no_early_termination {
                bail!(
                    "no-early-termination: applies to --mode dvr only (a slice composites no \
                     samples along rays)"
                );
            }
            let placed: Vec<&str> = [
                ("--slice-z", c.slice_z.is_some()),
                ("--slice-origin", c.slice_origin.is_some()),
                ("--slice-at", c.slice_at.is_some()),
            ]
            .into_iter()
            .filter_map(|(f, given)| given.then_some(f))
            .collect();
            if placed.len() > 1 {
                bail!(
                    "{}: give one of --slice-z, --slice-origin and --slice-at, not {} (each \
                     places the plane)",
                    placed[0].trim_start_matches('-'),
                    placed.join(" and ")
                );
            }
        }
        m => bail!("mode: expected dvr, mip or slice, found {m:?}"),
    }
    // Flags that another one makes moot.
    if c.ortho && c.fov.is_some() {
        bail!("fov: a perspective camera's field of view; --ortho draws in parallel projection (give one or the other)");
    }
    if c.level.is_some() && c.lod_bias != 0.0 {
        bail!(
            "lod-bias: shifts the automatic level of detail; --level {} draws one level (give \
             one or the other)",
            c.level.unwrap_or(0)
        );
    }
    if c.gpu_update.is_some() && c.backend == "cpu" {
        bail!("gpu-update: how the device back end updates its caches; --backend cpu has none");
    }
    check_loader_threads(c.loader_threads)?;
    if let Some(cam) = &c.camera {
        for (flag, given) in camera_flags {
            if given {
                bail!(
                    "{flag}: the camera comes from --camera {} (its position and projection); \
                     give one or the other",
                    cam.display()
                );
            }
        }
    }
    Ok(())
}

/// `--read-delay-ms` (a simulated slow disk, for `render` and `view`): at
/// most a minute a read, beyond which a view would not come in any useful
/// time.
pub fn check_read_delay(ms: u64) -> Result<()> {
    if ms > 60_000 {
        bail!("read-delay-ms: expected at most 60000 (a minute per brick read), found {ms}");
    }
    Ok(())
}

/// How a view's frames ended, as `--json` gives it: `complete`,
/// `complete_but_failed` (drawn from coarser data where bricks could not be
/// loaded), `no_progress` or `max_frames` (stopped by `--max-frames`).
pub fn stop_name(stop: Option<&Stop>) -> &'static str {
    match stop {
        Some(Stop::Complete) => "complete",
        Some(Stop::CompleteButFailed) => "complete_but_failed",
        Some(Stop::NoProgress) => "no_progress",
        None => "max_frames",
    }
}

/// `C[:COLOR[:LO,HI]]`.
fn parse_channel(
    s: &str,
    window: [f32; 2],
    channels: usize,
    omero: Option<&[OmeroChannel]>,
) -> Result<brickyard_render::reference::ChannelStyle> {
    let mut parts = s.splitn(3, ':');
    let c: usize = parts.next().unwrap_or("").trim().parse().with_context(|| {
        format!("channel: expected C[:COLOR[:LO,HI]] with C a channel number, found {s:?}")
    })?;
    if c >= channels {
        bail!("channel: {c} asked for but the store has {channels} channel(s)");
    }
    // The store's defaults for the channel.
    let dflt = omero.and_then(|o| o.get(c));
    let window = dflt
        .and_then(|d| d.window)
        .map_or(window, |w| [w[0] as f32, w[1] as f32]);
    let color = match parts.next().map(|x| x.trim().to_ascii_lowercase()) {
        None => dflt.map_or([1.0, 1.0, 1.0], |d| d.color.map(|x| x as f32 / 255.0)),
        Some(name) => {
            match name.as_str() {
                "red" => [1.0, 0.0, 0.0],
                "green" => [0.0, 1.0, 0.0],
                "blue" => [0.0, 0.0, 1.0],
                "cyan" => [0.0, 1.0, 1.0],
                "magenta" => [1.0, 0.0, 1.0],
                "yellow" => [1.0, 1.0, 0.0],
                "orange" => [1.0, 0.5, 0.0],
                "white" => [1.0, 1.0, 1.0],
                "gray" | "grey" => [0.5, 0.5, 0.5],
                hex => {
                    let h = hex.trim_start_matches('#');
                    let v = (h.len() == 6)
                    .then(|| u32::from_str_radix(h, 16).ok())
                    .flatten()
                    .with_context(|| {
                        format!("channel: colour {hex:?} in {s:?} is not a colour name or RRGGBB hex")
                    })?;
                    [16, 8, 0].map(|sh| ((v >> sh) & 0xff) as f32 / 255.0)
                }
            }
        }
    };
    let window = match parts.next() {
        None => window,
        Some(w) => {
            let p = parse_pair(w, "channel window")?;
            if !(p[0].is_finite() && p[1].is_finite() && p[0] < p[1]) {
                bail!("channel: window in {s:?}: expected LO,HI with LO < HI, both finite");
            }
            [p[0] as f32, p[1] as f32]
        }
    };
    Ok(brickyard_render::reference::ChannelStyle {
        channel: c,
        color,
        window,
        tf: None,
        levels: None,
    })
}

/// A transfer function as `--tf` and `--channel-tf` name it: a preset
/// (`TransferFunction::PRESETS`) over `window`, or a JSON file (a name
/// ending in `.json`, or any existing file that is not named like a
/// preset).
pub fn transfer_function(spec: &str, window: [f32; 2], flag: &str) -> Result<TransferFunction> {
    let name = spec.trim();
    let preset = TransferFunction::PRESETS
        .iter()
        .any(|p| p.eq_ignore_ascii_case(name));
    if !preset && (name.ends_with(".json") || std::path::Path::new(name).is_file()) {
        let text = std::fs::read_to_string(name)
            .with_context(|| format!("{flag}: {name}: cannot read"))?;
        // Without a `window`, the one a preset would take (the data's
        // default): `{"preset": "soft", "shading": true}` turns shading on
        // over the window `--tf soft` draws (it was refused, "window:
        // missing").
        let text = match serde_json::from_str::<serde_json::Value>(&text) {
            Ok(serde_json::Value::Object(mut o)) if !o.contains_key("window") => {
                o.insert("window".into(), serde_json::json!([window[0], window[1]]));
                serde_json::Value::Object(o).to_string()
            }
            _ => text,
        };
        return TransferFunction::from_json(&text)
            .map_err(|e| anyhow::anyhow!("{flag}: {name}: {e}"));
    }
    if !preset {
        bail!(
            "{flag}: {name:?} is neither a preset ({}) nor a transfer-function file (JSON, a name ending in .json)",
            TransferFunction::PRESETS.join(", ")
        );
    }
    TransferFunction::preset(name, window).map_err(|e| anyhow::anyhow!("{flag}: {e}"))
}

/// A per-channel flag (`--channel`, `--channel-tf`, `--channel-levels`)
/// given at most once per channel: `seen` holds the flags, channels and values so far.
fn once<'a>(
    seen: &mut Vec<(&'a str, usize, &'a String)>,
    flag: &'a str,
    ch: usize,
    value: &'a String,
) -> Result<()> {
    if let Some((_, _, first)) = seen.iter().find(|(f, c, _)| *f == flag && *c == ch) {
        bail!("{flag}: channel {ch} given twice (--{flag} {first} and --{flag} {value}); give each channel once");
    }
    seen.push((flag, ch, value));
    Ok(())
}

/// `C=LO-HI` or `C=L` of `--channel-levels`: the channel and its level
/// range, checked against the store's `levels`.
pub fn parse_channel_levels(t: &str, levels: usize) -> Result<(usize, [usize; 2])> {
    let bad = || anyhow::anyhow!("channel-levels: expected C=LO-HI or C=L, found {t:?}");
    let (ch, range) = t.split_once('=').ok_or_else(bad)?;
    let ch: usize = ch.trim().parse().map_err(|_| bad())?;
    let (lo, hi) = range.split_once('-').unwrap_or((range, range));
    let (lo, hi): (usize, usize) = (
        lo.trim().parse().map_err(|_| bad())?,
        hi.trim().parse().map_err(|_| bad())?,
    );
    if lo > hi || hi >= levels {
        bail!(
            "channel-levels: {t:?}: expected levels LO <= HI within 0-{} (the store has {levels} levels)",
            levels - 1
        );
    }
    Ok((ch, [lo, hi]))
}

/// An image size, `N` (square) or `WxH`, each between 1 and 16384.
pub fn parse_image_size(s: &str, what: &str) -> Result<[u32; 2]> {
    let bad = || anyhow::anyhow!("{what}: expected N or WxH between 1 and 16384, found {s:?}");
    let v: Vec<u32> = s
        .split('x')
        .map(|p| p.trim().parse::<u32>().map_err(|_| bad()))
        .collect::<Result<_>>()?;
    let wh = match v.as_slice() {
        [n] => [*n, *n],
        [w, h] => [*w, *h],
        _ => return Err(bad()),
    };
    if wh.iter().any(|&x| x == 0 || x > 16384) {
        return Err(bad());
    }
    Ok(wh)
}

/// `X,Y,Z`: three finite numbers.
pub fn parse_vec3(s: &str, what: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("{what}: expected X,Y,Z, found {s:?}"))?;
    match v[..] {
        [x, y, z] if v.iter().all(|a| a.is_finite()) => Ok([x, y, z]),
        _ => bail!("{what}: expected three finite numbers X,Y,Z, found {s:?}"),
    }
}

/// A data window `LO,HI` with `LO < HI` (the error names `what`).
pub fn parse_window(s: &str, what: &str) -> Result<[f64; 2]> {
    let p = parse_pair(s, what)?;
    if p[0].partial_cmp(&p[1]) != Some(std::cmp::Ordering::Less) {
        bail!("{what}: expected LO,HI with LO < HI, found {s:?}");
    }
    Ok(p)
}

fn parse_pair(s: &str, what: &str) -> Result<[f64; 2]> {
    let v: Vec<f64> = s
        .split([',', 'x'])
        .map(|p| p.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("{what}: expected two numbers, found {s:?}"))?;
    if v.len() != 2 {
        bail!("{what}: expected two numbers, found {s:?}");
    }
    Ok([v[0], v[1]])
}

impl RenderCmd {
    /// Parse from a full argument list (`brickyard render …`).
    /// `--backend` as given (auto, gpu or cpu).
    pub fn backend(&self) -> &str {
        &self.backend
    }

    /// The store drawn (what the ranks of a shared render must all see).
    pub fn store(&self) -> &std::path::Path {
        &self.store
    }

    pub fn try_parse_from(args: &[String]) -> Result<RenderCmd, clap::Error> {
        use clap::{Args as _, FromArgMatches as _};
        let cmd = RenderCmd::augment_args(clap::Command::new("render")).no_binary_name(false);
        let m = cmd.try_get_matches_from(args.iter().skip(1))?;
        RenderCmd::from_arg_matches(&m)
    }
}

/// Like [`run`], printing only each view's closing lines.
pub fn run_quiet(mut c: RenderCmd) -> Result<Vec<String>> {
    c.quiet = true;
    run(c)
}

/// How a view's line ends when bricks could not be loaded and coarser data
/// stands in for them (the CLI then exits with status 3).
pub const DEGRADED: &str = "that could not be loaded (drawn from coarser data)";

/// How a view's line begins (after its name) when it ended before it was
/// complete (`--max-frames`, or nothing more could arrive).
pub const STOPPED: &str = "stopped at ";

/// Render; returns one line per view written (file, how it ended).
pub fn run(c: RenderCmd) -> Result<Vec<String>> {
    run_shared(c, None)
}

/// [`run`] shared by the ranks of `share` (rank 0 writes the images and
/// prints; the others draw their part quietly).
pub fn run_shared(mut c: RenderCmd, share: Option<&mut dyn Share>) -> Result<Vec<String>> {
    if share.as_ref().is_some_and(|s| s.rank() > 0) {
        c.silent = true;
    }
    // Ranks on one node share its memory: the default budget is theirs.
    if let Some(s) = share.as_ref() {
        crate::memory::share_default_among(s.ranks_on_node());
    }
    let (raw, json) = (c.raw_f32, c.json);
    run_with(c, share, &mut |path, img| {
        write_view(path, &img, raw)?;
        // With --json, standard output holds JSON lines only.
        if json {
            eprintln!("wrote {}", path.display());
        } else {
            outln!("wrote {}", path.display());
        }
        Ok(())
    })
}

/// Write one view as `run` does: the PNG over black at `path`, and with
/// `raw_f32` the premultiplied image beside it (`.f32`: RGBA, little-endian
/// f32, rows top to bottom). Errors name the file.
pub fn write_view(
    path: &std::path::Path,
    img: &brickyard_render::Image,
    raw_f32: bool,
) -> Result<()> {
    if raw_f32 {
        let f = path.with_extension("f32");
        let bytes: Vec<u8> = img
            .rgba
            .as_flattened()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        brickyard_render::image::write_whole(&f, |w| w.write_all(&bytes))
            .with_context(|| format!("{}: cannot write", f.display()))?;
    }
    // (The error names the path.)
    img.write_png(path, [0.0, 0.0, 0.0, 1.0])
        .map_err(|e| anyhow::anyhow!("{e}"))
}

/// Render without printing or writing anything: each view's image (in
/// view order) with the file `run` would write it to (`--out`, or a
/// turntable's numbered files beside it).
pub fn views(c: RenderCmd) -> Result<Vec<(PathBuf, brickyard_render::Image)>> {
    Ok(views_noted(c)?.0)
}

/// [`views`], with each view's closing line (its file and how it ended:
/// "complete", or "complete but for N brick(s) that could not be
/// loaded …", "stopped at …"), as `run` prints them.
#[allow(clippy::type_complexity)]
pub fn views_noted(
    mut c: RenderCmd,
) -> Result<(Vec<(PathBuf, brickyard_render::Image)>, Vec<String>)> {
    c.silent = true;
    let mut out = vec![];
    WARNINGS.with(|w| *w.borrow_mut() = Some(vec![]));
    let lines = run_with(c, None, &mut |path, img| {
        out.push((path.to_path_buf(), img));
        Ok(())
    });
    let warned = WARNINGS.with(|w| w.borrow_mut().take()).unwrap_or_default();
    let mut lines = lines?;
    lines.extend(warned);
    Ok((out, lines))
}

thread_local! {
    /// The warnings of a run of [`views_noted`], whose caller (Python)
    /// raises them as its own, where a run of the CLI prints them.
    static WARNINGS: std::cell::RefCell<Option<Vec<String>>> = const { std::cell::RefCell::new(None) };
}

/// A warning or note about the run (`KIND: …` on stderr unless the run is
/// silent), or kept for the caller of [`views_noted`].
fn tell(silent: bool, kind: &str, line: String) {
    let kept = WARNINGS.with(|w| match w.borrow_mut().as_mut() {
        Some(v) => {
            v.push(format!("{kind}: {line}"));
            true
        }
        None => false,
    });
    if !kept && !silent {
        eprintln!("{kind}: {line}");
    }
}

/// [`views`]' images alone.
pub fn images(c: RenderCmd) -> Result<Vec<brickyard_render::Image>> {
    Ok(views(c)?.into_iter().map(|(_, img)| img).collect())
}

/// Print unless the run is silent.
macro_rules! say {
    ($silent:expr, $($t:tt)*) => {
        if !$silent {
            outln!($($t)*);
        }
    };
}

/// Print to stderr unless the run is silent.
macro_rules! say_err {
    ($silent:expr, $($t:tt)*) => {
        if !$silent {
            eprintln!($($t)*);
        }
    };
}

/// A line of text about a shared render: on stdout, or with `--json` (whose
/// stdout holds JSON lines only) on stderr.
macro_rules! say_text {
    ($json:expr, $silent:expr, $($t:tt)*) => {
        if $json {
            say_err!($silent, $($t)*);
        } else {
            say!($silent, $($t)*);
        }
    };
}

/// `--only-labels` / `--hide-labels`: the selection of labels drawn, for
/// a run that draws a label image's colours (`labels`).
fn label_select(c: &RenderCmd, labels: bool) -> Result<Option<LabelSelect>> {
    let (text, hide, flag) = match (&c.only_labels, &c.hide_labels) {
        (Some(t), _) => (t, false, "only-labels"),
        (None, Some(t)) => (t, true, "hide-labels"),
        (None, None) => return Ok(None),
    };
    if !labels {
        bail!(
            "{flag}: applies to a label image's colours (a store's labels/NAME, --tf labels, \
             or --labels NAME over a slice)"
        );
    }
    let ids = LabelSelect::parse_ids(text).map_err(|e| anyhow::anyhow!("{flag}: {e}"))?;
    Ok(Some(LabelSelect::new(ids, hide)))
}

/// The render of [`run`] and [`images`]: `sink` receives each view's
/// image and the file it is meant for.
fn run_with(
    c: RenderCmd,
    share: Option<&mut dyn Share>,
    sink: &mut dyn FnMut(&std::path::Path, brickyard_render::Image) -> Result<()>,
) -> Result<Vec<String>> {
    if c.labels.is_some() || c.label_opacity.is_some() {
        return run_with_labels(c, share, sink);
    }
    run_one(c, share, sink)
}

/// `--labels NAME`: the image's slice, then the slice of the store's label
/// image `labels/NAME` in the labels' colours, laid over it
/// ([`crate::labels::overlay`]). The two runs come one after the other,
/// each within `--memory` less the other's image, which waits for the
/// second.
fn run_with_labels(
    mut c: RenderCmd,
    share: Option<&mut dyn Share>,
    sink: &mut dyn FnMut(&std::path::Path, brickyard_render::Image) -> Result<()>,
) -> Result<Vec<String>> {
    let Some(name) = c.labels.take() else {
        bail!("label-opacity: applies with --labels NAME (the label image drawn over the slice)");
    };
    let opacity = c.label_opacity.take().unwrap_or(0.5);
    let (silent, json) = (c.silent, c.json);
    if !(opacity > 0.0 && opacity <= 1.0) {
        bail!("label-opacity: expected an opacity above 0 and at most 1, found {opacity}");
    }
    if c.mode != "slice" {
        bail!(
            "labels: label images are drawn over slices (--mode slice); --mode {} draws the image alone",
            c.mode
        );
    }
    if c.tf.as_deref() == Some("labels") {
        bail!("labels: --tf labels draws a label image alone; with --labels NAME the labels come over the image, drawn through --tf");
    }
    if share.as_ref().is_some_and(|s| s.size() > 1) {
        bail!("labels: a slice with labels draws on one process");
    }
    if c.turntable.is_some() || c.views.is_some() || c.stereo.is_some() || c.multiplex.is_some() {
        bail!("labels: one view at a time (no --turntable, --views, --stereo or --multiplex)");
    }
    let dir = crate::labels::label_store(&c.store, &name)?;
    let [w, h] = parse_image_size(&c.size, "size")?;
    let held = w as u64 * h as u64 * std::mem::size_of::<[f32; 4]>() as u64;
    // The labels' selection is the second run's: checked before the first
    // draws.
    label_select(&c, true)?;
    let mut lc = c.clone();
    (c.only_labels, c.hide_labels) = (None, None);
    lc.store = dir;
    lc.tf = Some("labels".into());
    lc.window = None;
    lc.channels.clear();
    lc.derive = None;
    lc.save_camera = None;
    lc.silent = true;
    let mut why_less = None;
    if let Some(m) = &c.memory {
        let m = crate::memory::parse_bytes(m).context("--memory")?;
        if m <= held {
            bail!(
                "memory: {} cannot hold the labels' slice ({}) beside the image's",
                human_bytes(m),
                human_bytes(held)
            );
        }
        c.memory = Some((m - held).to_string());
        lc.memory = c.memory.clone();
        why_less = Some(format!(
            "labels: each of the two slices (the image's, the labels') is drawn within --memory \
             {} less the other's image ({}): {}",
            human_bytes(m),
            human_bytes(held),
            human_bytes(m - held)
        ));
    }
    let with_why = |e: anyhow::Error| match &why_less {
        Some(w) => e.context(w.clone()),
        None => e,
    };
    // The image's slice first (a budget too small for it is refused
    // before any work), then the labels', laid over it.
    let mut shown = vec![];
    let lines = run_one(c, share, &mut |path, img| {
        shown.push((path.to_path_buf(), img));
        Ok(())
    })
    .map_err(with_why)?;
    let mut labels = vec![];
    let label_lines = run_one(lc, None, &mut |_, img| {
        labels.push(img);
        Ok(())
    })
    .map_err(with_why)?;
    // The labels' lines join the image's: bricks of the labels that could
    // not be loaded end the command with status 3 as the image's do.
    let label_lines: Vec<String> = label_lines
        .iter()
        .map(|l| {
            let detail = l.split_once(": ").map_or(l.as_str(), |(_, d)| d);
            format!("labels {name}: {detail}")
        })
        .collect();
    if !silent && !json {
        for l in &label_lines {
            outln!("{l}");
        }
    }
    if shown.len() != labels.len() {
        bail!(
            "labels: {} image(s) of the slice, {} of the labels",
            shown.len(),
            labels.len()
        );
    }
    for ((path, mut img), lab) in shown.into_iter().zip(&labels) {
        crate::labels::overlay(&mut img, lab, opacity)?;
        sink(&path, img)?;
    }
    Ok(lines.into_iter().chain(label_lines).collect())
}

/// The residency octree's depth within a budget ([`fit_octree_depth`]).
pub struct OctreeFit {
    /// The depth drawn through.
    pub depth: u32,
    /// What its tables and the traversal's per-frame tables take
    /// ([`brickyard_render::octree::Octree::working_bytes`]), to set aside
    /// in the budget.
    pub bytes: u64,
    /// Where the depth asked for was lowered, a note saying so.
    pub note: Option<String>,
}

/// The octree's tables and the traversal's per frame grow 8× a depth
/// (depth 7 over three levels took 600 MiB, past a 128 MiB --memory): a
/// depth `asked` that would take more than a quarter of `total` is lowered
/// (the octree only skips space faster; the image is the same), with a
/// note. For `render` and the viewer alike.
pub fn fit_octree_depth(asked: u32, levels: usize, channels: usize, total: u64) -> OctreeFit {
    use brickyard_render::octree::{Octree, MIN_DEPTH};
    let cost = |d: u32| Octree::working_bytes(d, levels, channels.max(1));
    let mut depth = asked;
    while depth > MIN_DEPTH && cost(depth) > total / 4 {
        depth -= 1;
    }
    let note = (depth < asked).then(|| {
        format!(
            "note: octree-depth {asked} would take about {} of --memory {}: drawing through \
             depth {depth} ({}; the image is the same, space is skipped in larger steps)",
            human_bytes(cost(asked)),
            human_bytes(total),
            human_bytes(cost(depth))
        )
    });
    OctreeFit {
        depth,
        bytes: cost(depth),
        note,
    }
}

/// The deepest octree at most `asked` whose device tables (and a
/// transfer function's room beside them) a device's storage buffer of
/// `limit` bytes holds.
pub fn fit_octree_to_device(asked: u32, levels: usize, channels: usize, limit: u64) -> OctreeFit {
    use brickyard_render::octree::{Octree, MIN_DEPTH};
    // (Transfer functions, channel styles and a label selection: within
    // 1 MiB.)
    let cost = |d: u32| Octree::device_table_bytes(d, levels, channels.max(1)) + (1 << 20);
    let mut depth = asked;
    while depth > MIN_DEPTH && cost(depth) > limit {
        depth -= 1;
    }
    let note = (depth < asked).then(|| {
        format!(
            "note: octree-depth {asked}: its tables would take {} on the device, past its limit \
             of {} for one buffer: drawing through depth {depth} (the image is the same, space \
             is skipped in larger steps)",
            human_bytes(cost(asked)),
            human_bytes(limit)
        )
    });
    OctreeFit {
        depth,
        bytes: cost(depth),
        note,
    }
}

/// A `--turntable` count: 1 to 3600 views, said so for any other value (a
/// negative one got the parser's "not in 0..=4294967295").
fn parse_views(s: &str) -> std::result::Result<u32, String> {
    s.trim()
        .parse::<i64>()
        .ok()
        .filter(|n| (1..=3600).contains(n))
        .map(|n| n as u32)
        .ok_or_else(|| format!("expected 1 to 3600 views, found {s}"))
}

/// [`run_with`] of one store.
fn run_one(
    c: RenderCmd,
    mut share: Option<&mut dyn Share>,
    sink: &mut dyn FnMut(&std::path::Path, brickyard_render::Image) -> Result<()>,
) -> Result<Vec<String>> {
    let silent = c.silent;
    // Several ranks, and how they share the render.
    let shared = match (&c.distribute, share.as_ref().map(|s| s.size())) {
        (Some(d), _) if d != "image" && d != "data" => {
            bail!("distribute: expected image or data, found {d:?}")
        }
        (_, Some(n)) if n > 1 => Some(share.as_ref().unwrap().split()),
        _ => None,
    };
    if shared.is_some() {
        if c.debug.is_some() {
            bail!("distribute: --debug draws on one process");
        }
        if c.progressive.is_some() && c.backend == "gpu" {
            bail!("distribute: --progressive accumulates on the CPU of each rank (the device's accumulation draws whole frames of the whole ray); use --backend cpu");
        }
        if c.derive.is_some() {
            bail!("distribute: live derived channels draw on one process");
        }
    }
    if c.max_frames == 0 {
        bail!("max-frames: expected at least 1 frame, found 0");
    }
    if let Some(n) = c.turntable.filter(|n| !(1..=3600).contains(n)) {
        // (A view a tenth of a degree apart at most: more is a typo, not
        // a turntable, and each view is a file.)
        bail!("turntable: expected 1 to 3600 views, found {n}");
    }
    if let Some(e) = c.out.extension().filter(|e| !e.eq_ignore_ascii_case("png")) {
        bail!(
            "{}: images are written as PNG; expected a name ending in .png, found .{}",
            c.out.display(),
            e.to_string_lossy()
        );
    }
    check_mode_flags(&c)?;
    let (azimuth, elevation) = (c.azimuth.unwrap_or(30.0), c.elevation.unwrap_or(20.0));
    let fov = c.fov.unwrap_or(35.0);
    let samples_per_voxel = c.samples_per_voxel.unwrap_or(1.0);
    for (flag, v) in [("azimuth", azimuth), ("elevation", elevation)] {
        if !v.is_finite() {
            bail!("{flag}: expected a finite angle in degrees, found {v}");
        }
    }
    if !(fov > 0.0 && fov < 180.0) {
        bail!(
            "fov: expected a vertical field of view between 0 and 180 degrees (exclusive), found {fov}"
        );
    }
    if !(samples_per_voxel > 0.0 && samples_per_voxel <= 64.0) {
        bail!(
            "samples-per-voxel: expected a number of samples per voxel above 0 and at most 64, found {samples_per_voxel}"
        );
    }
    check_read_delay(c.read_delay_ms)?;
    if c.requests == Some(0) {
        bail!("requests: expected at least 1 request per frame, found 0: no brick could ever be asked for");
    }
    if !c.lod_bias.is_finite() {
        bail!(
            "lod-bias: expected a finite number of levels (negative: finer), found {}",
            c.lod_bias
        );
    }
    // The camera's file is none of the image's (it was written, then
    // overwritten by the image without a word).
    if let Some(cam) = &c.save_camera {
        let out = (!c.in_memory).then_some(&c.out);
        let images = [
            out.cloned(),
            out.filter(|_| c.raw_f32).map(|o| o.with_extension("f32")),
        ];
        let same = |a: &std::path::Path, b: &std::path::Path| {
            a == b
                || std::fs::canonicalize(a)
                    .ok()
                    .zip(std::fs::canonicalize(b).ok())
                    .is_some_and(|(x, y)| x == y)
        };
        if let Some(img) = images.iter().flatten().find(|i| same(cam, i)) {
            bail!(
                "save-camera: {} is the image's own file ({}); give the camera another file \
                 (e.g. view.json)",
                cam.display(),
                if img.extension().is_some_and(|e| e == "f32") {
                    "--raw-f32"
                } else {
                    "--out"
                }
            );
        }
    }
    let files = [
        (Some(&c.out).filter(|_| !c.in_memory), "the image"),
        (c.save_camera.as_ref(), "the camera (--save-camera)"),
    ];
    for (file, what) in files {
        let Some(file) = file else { continue };
        if let Some(parent) = file.parent().filter(|p| !p.as_os_str().is_empty()) {
            if !parent.is_dir() {
                bail!(
                    "{}: cannot write {what} there: {} is not an existing folder",
                    file.display(),
                    parent.display()
                );
            }
        }
        // Found before the render, not after it.
        if file.is_dir() {
            bail!("{}: cannot write {what}: it is a folder", file.display());
        }
        if let Err((dir, e)) = crate::can_create_beside(file) {
            bail!(
                "{}: cannot write {what}: cannot create a file in {} ({e})",
                file.display(),
                dir.display()
            );
        }
        if file.exists() {
            if let Err(e) = std::fs::OpenOptions::new().append(true).open(file) {
                bail!("{}: cannot write {what}: {e}", file.display());
            }
        }
    }
    let weights = c.region_weights.as_deref().unwrap_or("view");
    if !matches!(weights, "view" | "data" | "uniform") {
        bail!("region-weights: expected view, data or uniform, found {weights:?}");
    }
    // It balances a data-parallel render's regions; with another split,
    // or none, it would be ignored.
    if c.region_weights.is_some() && c.distribute.as_deref() != Some("data") {
        bail!(
            "region-weights: only with --distribute data (it balances the regions of a \
             data-parallel render), found --region-weights {weights} {}",
            match c.distribute.as_deref() {
                None => "without --distribute".to_string(),
                Some(d) => format!("with --distribute {d}"),
            }
        );
    }
    let data_split = shared == Some(Split::Data);
    if data_split && (c.views.is_some() || c.stereo.is_some() || c.multiplex.is_some()) {
        bail!("distribute data: one view per image (no --views, --stereo or --multiplex)");
    }
    let [w, h] = parse_image_size(&c.size, "size")?;
    let (n_views, layout) = view_layout(&c)?;
    // The image written for view `v`: the N views composed as asked, at
    // `--out` (numbered for turntables).
    let compose = |img: brickyard_render::image::Image| -> Result<brickyard_render::image::Image> {
        match &layout {
            // (Side by side is the image as drawn: not copied.)
            Some(brickyard_render::views::Layout::SideBySide) if n_views == 2 => Ok(img),
            Some(l) => brickyard_render::views::compose(&img, n_views, l, [0.0, 0.0, 0.0, 1.0])
                .map_err(|e| anyhow::anyhow!("views: {e}")),
            None => Ok(img),
        }
    };
    let out_path = |v: u32| match c.turntable {
        Some(_) => {
            let stem = c
                .out
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            c.out.with_file_name(format!("{stem}-{v:04}.png"))
        }
        None => c.out.clone(),
    };
    let TraversalChoice {
        traversal,
        depth: octree_depth,
        debug,
        backend: backend_choice,
        gpu_update,
    } = traversal_options(&c)?;
    // Shared: each rank draws on the CPU, or with --backend gpu on a
    // device of its own (adapter `rank` modulo the adapters).
    let backend_choice = match shared {
        Some(_) if c.backend == "gpu" => "gpu".to_string(),
        Some(_) => "cpu".to_string(),
        None => backend_choice,
    };
    let adapter = share.as_ref().map_or(0, |s| s.rank());
    if backend_choice != c.backend && shared.is_none() {
        say_err!(silent, "{}", auto_takes_cpu());
    }
    let info = inspect(&c.store)?;
    if let Some(why) = info.incomplete {
        bail!("{}: the store is incomplete: {why}", c.store.display());
    }
    // A label image shows its labels unless --tf says otherwise.
    let tf_name = match c.tf.as_deref() {
        Some(t) => t,
        None if c.mode != "mip"
            && c.channels.is_empty()
            && c.derive.is_none()
            && n_views == 1
            && info.label_image =>
        {
            "labels"
        }
        None => "soft",
    };
    let labels = tf_name == "labels";
    let select = label_select(&c, labels)?;
    if labels {
        let why = if c.mode == "mip" {
            Some("--mode mip draws a label image's values through another transfer function; labels are coloured in slices and in 3D (--mode slice or dvr)".to_string())
        } else if c.progressive.is_some() {
            Some("label surfaces are drawn whole in each frame (no --progressive)".to_string())
        } else if c.traversal != "page-table" || c.debug.is_some() {
            Some(
                "labels are drawn through the page tables (no --traversal octree or --debug)"
                    .to_string(),
            )
        } else if shared.is_some() {
            Some("labels draw on one process".to_string())
        } else if !c.channels.is_empty() {
            Some("a label image has one channel (no --channel)".to_string())
        } else if c.derive.is_some() {
            Some("labels are drawn as stored (no --derive)".to_string())
        } else if n_views > 1 {
            Some("one view (no --views, --stereo or --multiplex)".to_string())
        } else if c.window.is_some() {
            Some("label colours take no --window".to_string())
        } else {
            None
        };
        if let Some(why) = why {
            bail!("tf: labels: {why}");
        }
    }
    let l0 = zarr::open(&c.store, 0)?;
    let m = l0.meta().clone();
    // Labels are sampled as f32: beyond 2^24 neighbouring labels share a
    // value (and so a colour). Said, on stderr, also in the labels' run of
    // --labels.
    if labels {
        let exact = brickyard_render::params::EXACT_LABELS as f64;
        if let Some(s) = info.levels.first().and_then(|l| l.stats.as_ref()) {
            if s.max > exact || s.min < -exact {
                tell(
                    false,
                    "warning",
                    format!(
                        "{}: labels reach {}; labels beyond {} (2^24) are drawn from 32-bit \
                     floats, so neighbouring ones there may share a colour and cannot be chosen \
                     apart (renumber them below 2^24 to draw each alone)",
                        c.store.display(),
                        if s.max > exact { s.max } else { s.min },
                        brickyard_render::params::EXACT_LABELS
                    ),
                );
            }
        }
    }
    // Only some labels drawn: where they lie, from the label statistics
    // (bricks none of them reaches are crossed). Unreadable statistics
    // only cost that.
    let select = match select {
        Some(s) if labels && !s.hide => {
            match crate::label_stats::with_boxes(s.clone(), &c.store, m.dims) {
                Ok(s) => {
                    // Labels named that the image does not hold draw
                    // nothing: said (on stderr, also in the labels' run
                    // of --labels, which is otherwise silent).
                    // None of them: nothing of what was asked could
                    // be drawn, an error (it wrote an image of no
                    // label and exited 0).
                    if let Some(b) = &s.boxes {
                        let (found, named) = (b.boxes.len(), s.ids.len());
                        if found == 0 {
                            bail!(
                                "only-labels: {} in {} (its table of label statistics): \
                                     nothing would be drawn",
                                match named {
                                    1 => format!("label {} is not", s.ids_text()),
                                    n => format!(
                                        "none of the {n} labels named ({}) is",
                                        s.ids_text()
                                    ),
                                },
                                c.store.display(),
                            );
                        }
                        if found < named {
                            tell(
                                false,
                                "note",
                                format!(
                                    "only-labels: {} of the {named} label(s) named {} not \
                                     in {} (its table of label statistics)",
                                    named - found,
                                    if named - found == 1 { "is" } else { "are" },
                                    c.store.display(),
                                ),
                            );
                        }
                    }
                    Some(s)
                }
                Err(e) => {
                    tell(
                        silent,
                        "warning",
                        format!("label statistics not used: {e:#}"),
                    );
                    Some(s)
                }
            }
        }
        s => s,
    };
    let spacing = m.spacing.unwrap_or([1.0; 3]);
    let extent = world_extent(m.dims, spacing);
    let mut levels = vec![];
    for l in 0..info.levels.len() {
        levels.push(zarr::open(&c.store, l)?.meta().dims);
    }
    let mut scene = Scene::new(extent, levels);
    scene.stop = c.stop.clone();
    // The store's channel the view shows (DVR) or the first one listed.
    let first_channel = c
        .channels
        .first()
        .and_then(|x| x.split(':').next()?.trim().parse::<usize>().ok())
        .unwrap_or(0);
    let opt_bytes = |v: &Option<String>, flag: &str| {
        v.as_deref()
            .map(|x| crate::memory::parse_bytes(x).with_context(|| format!("--{flag}")))
            .transpose()
    };
    let memory = opt_bytes(&c.memory, "memory")?;
    // A live derived channel's filters get at most a quarter of --memory
    // (as `process` gives its filters), for the loader threads' brick
    // reads at once; what they take comes out of the pool's and the host
    // cache's shares. Checked before any brick is computed.
    let mut filter_bytes = 0;
    let derived = match &c.derive {
        Some(p) => {
            if c.channels.len() > 1 {
                bail!("derive: a derived channel is computed from one channel; give at most one --channel");
            }
            if c.channels.is_empty() && m.channels > 1 {
                say_err!(
                    silent,
                    "note: --derive computes from channel 0 of {} (choose another with --channel C)",
                    m.channels
                );
            }
            let (d, bytes) = crate::derive::Derived::new_within(
                &c.store,
                p,
                first_channel,
                memory,
                c.loader_threads,
                c.brick,
            )?;
            filter_bytes = bytes;
            if info.label_image {
                if let Some(n) = d.pipeline.label_ids_note(&c.store.display().to_string()) {
                    tell(silent, "note", n);
                }
            }
            Some(d)
        }
        None => None,
    };
    let (lo, hi) = match &c.window {
        // Label colours take no window.
        None if labels => (0.0, 1.0),
        Some(wd) => {
            let [lo, hi] = parse_window(wd, "window")?;
            (lo, hi)
        }
        None if derived.is_some() => {
            let d = derived.as_ref().unwrap();
            let w =
                crate::window::window_of_levels_in(info.levels.len(), 0, d.read_limit(), |l| {
                    d.open_level(l)
                })?;
            crate::window::give_back_freed_memory();
            w.unwrap_or((0.0, 1.0))
        }
        None => {
            let ch = first_channel.min(m.channels.saturating_sub(1));
            crate::window::auto_window(&c.store, info.levels.len(), ch)?
                .or_else(|| {
                    info.levels
                        .iter()
                        .rev()
                        .find_map(|l| l.stats.as_ref().map(|s| (s.min, s.max)))
                        // One value everywhere (a blank or constant volume)
                        // has no range: the unit window, as the viewer.
                        .filter(|(lo, hi)| hi > lo)
                })
                .unwrap_or((0.0, 1.0))
        }
    };
    let mut tf = match labels {
        true => TransferFunction::preset("linear", [lo as f32, hi as f32])?,
        false => transfer_function(tf_name, [lo as f32, hi as f32], "tf")?,
    };
    check_octree_shading(traversal, &tf, tf_name, c.channels.len() <= 1)?;
    let projection = if c.ortho {
        Projection::Orthographic {
            height: extent.iter().cloned().fold(0.0, f64::max) * 1.2,
        }
    } else {
        Projection::Perspective { fov_y_deg: fov }
    };
    // `--camera`: the camera, and for a slice the plane saved with it
    // (where the options do not place it themselves).
    let camera_file = match &c.camera {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("{}: cannot read", p.display()))?;
            Some(
                CameraFile::from_json(&text)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?,
            )
        }
        None => None,
    };
    let mode = match c.mode.as_str() {
        "dvr" => RenderMode::Dvr,
        "mip" => RenderMode::Mip,
        "slice" => {
            let saved = camera_file.as_ref();
            let max = brickyard_core::camera::MAX_COORD;
            let origin = match (&c.slice_origin, &c.slice_at) {
                (Some(o), _) => {
                    let v = parse_vec3(o, "slice-origin")?;
                    if v.iter().any(|a| a.abs() > max) {
                        bail!("slice-origin: expected coordinates within ±{max:e}, found {o:?}");
                    }
                    v
                }
                // Physical coordinates: voxel i's centre lies at
                // translation + i·spacing there, at (i + ½)·spacing in the
                // renderer's world.
                (None, Some(a)) => {
                    let v = parse_vec3(a, "slice-at")?;
                    if v.iter().any(|a| a.abs() > max) {
                        bail!("slice-at: expected coordinates within ±{max:e}, found {a:?}");
                    }
                    let t = m.origin.unwrap_or([0.0; 3]);
                    [0, 1, 2].map(|k| v[k] - t[2 - k] + 0.5 * spacing[2 - k])
                }
                (None, None)
                    if c.slice_z.is_none() && saved.is_some_and(|f| f.slice_origin.is_some()) =>
                {
                    saved.and_then(|f| f.slice_origin).unwrap()
                }
                (None, None) => {
                    let z = c.slice_z.unwrap_or(0.5);
                    if !(0.0..=1.0).contains(&z) {
                        bail!("slice-z: expected a fraction of the depth from 0 to 1, found {z}");
                    }
                    let z = brickyard_core::camera::slice_centre(extent[2], m.dims[0], z);
                    [extent[0] / 2.0, extent[1] / 2.0, z]
                }
            };
            let normal = match &c.slice_normal {
                Some(n) => parse_vec3(n, "slice-normal")?,
                None => saved
                    .and_then(|f| f.slice_normal)
                    .unwrap_or([0.0, 0.0, 1.0]),
            };
            let ln = brickyard_core::camera::length(normal);
            if !(1e-12..=f64::MAX).contains(&ln) {
                bail!(
                    "slice-normal: expected a non-zero vector of finite length, found {normal:?}"
                );
            }
            // A plane that misses the volume would draw a blank image and
            // call it complete.
            let side = |k: usize| {
                let p = [0, 1, 2].map(|a| if k >> a & 1 == 1 { extent[a] } else { 0.0 });
                (0..3).map(|a| (p[a] - origin[a]) * normal[a]).sum::<f64>()
            };
            let (lo, hi) = (0..8)
                .map(side)
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                    (l.min(v), h.max(v))
                });
            if lo > 0.0 || hi < 0.0 {
                if let Some(a) = &c.slice_at {
                    // Said in the coordinates given: the voxels' outer
                    // faces, translation added.
                    let t = m.origin.unwrap_or([0.0; 3]);
                    let from = [0, 1, 2].map(|k| t[2 - k] - 0.5 * spacing[2 - k]);
                    let to = [0, 1, 2].map(|k| from[k] + extent[k]);
                    bail!(
                        "slice-at: the plane through {a} with normal {normal:?} misses the \
                         volume, which spans {from:?} to {to:?} (x, y, z, the store's physical \
                         coordinates{})",
                        m.unit
                            .as_deref()
                            .map(|u| format!(", {u}"))
                            .unwrap_or_default()
                    );
                }
                bail!(
                    "slice-origin: the plane through {origin:?} with normal {normal:?} misses the \
                     volume, which spans [0, 0, 0] to {extent:?} (world x, y, z)"
                );
            }
            RenderMode::Slice { origin, normal }
        }
        s => bail!("mode: expected dvr, mip or slice, found {s:?}"),
    };
    // The default view fits the volume into the image (one view's,
    // `w × h`), its width as well as its height.
    let camera = match &camera_file {
        Some(f) => f.camera,
        None => match &mode {
            RenderMode::Slice { origin, normal } => {
                Camera::fit_plane(extent, *origin, *normal, w, h)
            }
            _ => Camera::fit_image(extent, azimuth, elevation, projection, w, h),
        },
    };
    // A field of view so narrow that the eye fitting the volume into it
    // stands beyond the coordinates a camera takes: said of --fov (the
    // camera's check would name its eye, which the user never gave).
    if camera_file.is_none() && c.fov.is_some() {
        let max = brickyard_core::camera::MAX_COORD;
        if camera.eye.iter().any(|v| !v.is_finite() || v.abs() > max) {
            bail!(
                "fov: {fov}° is too narrow: the camera that fits the volume into it would stand beyond ±{max:e} from it; give a wider field of view"
            );
        }
    }
    // A slice's camera file keeps its plane, so that `--camera` draws the
    // same slice; the view is drawn with the camera and plane as the file
    // gives them back (a JSON number may read back an ulp off), so that
    // it draws the same image too.
    let (camera, mode) = match &c.save_camera {
        Some(p) => {
            let plane = match &mode {
                RenderMode::Slice { origin, normal } => Some((*origin, *normal)),
                _ => None,
            };
            let text = CameraFile {
                camera,
                slice_origin: plane.map(|p| p.0),
                slice_normal: plane.map(|p| p.1),
            }
            .to_json();
            brickyard_render::image::write_whole(p, |w| w.write_all(text.as_bytes()))
                .with_context(|| format!("{}: cannot write", p.display()))?;
            let back = CameraFile::from_json(&text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            let mode = match (mode, back.slice_origin, back.slice_normal) {
                (RenderMode::Slice { .. }, Some(origin), Some(normal)) => {
                    RenderMode::Slice { origin, normal }
                }
                (m, _, _) => m,
            };
            (back.camera, mode)
        }
        None => (camera, mode),
    };
    let batch = !c.stream;
    // A device back end's driver lives in this process: its share comes
    // off the budget before the split (and `auto` takes the CPU where the
    // budget leaves no room for it).
    let device = crate::backend::plan_device(&backend_choice, adapter, memory);
    if let Some(n) = &device.note {
        say_err!(silent, "{n}");
    }
    let backend_choice = device.choice.clone();
    let pool_given = opt_bytes(&c.pool, "pool")?;
    if pool_given == Some(0) {
        bail!("pool: expected a size above 0 (e.g. 256MiB)");
    }
    let pixels = n_views as u64 * w as u64 * h as u64;
    let ranks = share.as_ref().map_or(1, |s| s.size());
    let host_given = opt_bytes(&c.host, "host")?;
    // `--progressive`: the samples it keeps get a quarter of --memory,
    // set aside before the pool and host cache take their shares (frames
    // beyond what it holds are not drawn, and the run says so).
    let samples_bytes = match c.progressive {
        Some(_) => memory.unwrap_or_else(crate::memory::default_memory) / 4,
        None => 0,
    };
    // The residency octree: its tables and the traversal's per frame grow
    // 8× a depth (depth 7 over three levels took 600 MiB, past a 128 MiB
    // --memory). They are set aside in --memory; a depth that would take
    // more than a quarter of it is lowered (the octree only skips space
    // faster; the image is the same), and the run says so.
    let (octree_depth, octree_bytes) = if traversal == Traversal::Octree {
        let total = memory.unwrap_or_else(crate::memory::default_memory);
        let fit = fit_octree_depth(octree_depth, info.levels.len(), m.channels, total);
        if let Some(n) = &fit.note {
            say_err!(silent, "{n}");
        }
        (fit.depth, fit.bytes)
    } else {
        (octree_depth, 0)
    };
    let split_for = |device_bytes: u64| {
        crate::memory::split_with_shares(
            memory,
            pool_given,
            host_given,
            pixels + exchange_pixels(shared, ranks, pixels),
            info.levels.len(),
            device_bytes + octree_bytes,
            (filter_bytes, samples_bytes),
        )
    };
    let mut split = split_for(device.bytes).map_err(|e| {
        // The driver's share is named only where it is what leaves too
        // little (the split without it would do), not for a bad --host.
        if device.bytes == 0 || split_for(0).is_err() {
            e
        } else if backend_choice == "cpu" {
            // `auto` looked for a device and drew on the CPU; the driver
            // it loaded stays.
            e.context(format!(
                "--backend auto: the graphics driver loaded to look for a device holds {} of \
                 --memory (--backend cpu does without)",
                human_bytes(device.bytes)
            ))
        } else {
            e.context(format!(
                "--backend {backend_choice}: the device back end takes {} of --memory for its \
                 driver (--backend cpu does without)",
                human_bytes(device.bytes)
            ))
        }
    })?;
    device.take_from(&mut split, pool_given)?;
    crate::memory::watch(split.total);
    // A padded brick of the pool (its cell ranges included), to size the
    // batch's requests and uploads.
    let dtype = match &derived {
        Some(d) => d.dtype,
        None => m.dtype,
    };
    let slot_bytes = VmConfig {
        brick: [c.brick; 3],
        ..Default::default()
    }
    .slot_bytes(dtype);
    // A batch asks for as much as the pool and the host cache can take at
    // once (bricks waiting to be written are held by the host cache).
    let requests_for = |pool: u64, host: u64| {
        crate::frames::requests_per_frame(
            pool,
            host,
            slot_bytes,
            if batch {
                crate::frames::BATCH_REQUESTS
            } else {
                crate::frames::STREAM_REQUESTS
            },
        )
    };
    let cfg = VmConfig {
        brick: [c.brick; 3],
        pool_bytes: split.pool,
        upload_bytes_per_frame: match opt_bytes(&c.upload, "upload")? {
            Some(u) if u < (c.brick + 2).pow(3) * dtype.size() as u64 => bail!(
                "upload: {u} bytes per frame is less than one padded brick ({} bytes): no brick could ever be written into the pool",
                (c.brick + 2).pow(3) * dtype.size() as u64
            ),
            Some(u) => match device.upload_cap() {
                Some(cap) if u > cap => bail!(
                    "upload: a device back end writes at most {} of bricks per frame (its \
                     staging buffer is host memory, set aside in --memory); found {}",
                    human_bytes(cap),
                    human_bytes(u)
                ),
                _ => u,
            },
            None => {
                let u = if batch { split.pool } else { 64 << 20 };
                u.min(device.upload_cap().unwrap_or(u64::MAX))
            }
        },
        request_cap: c.requests.unwrap_or(requests_for(split.pool, split.host)),
        ..Default::default()
    };
    // The store's channel defaults (names, colours, windows); an explicit
    // --window overrides their windows.
    let omero = brickyard_store::omezarr::read_omero(&c.store)?.map(|mut o| {
        if c.window.is_some() {
            for ch in &mut o {
                ch.window = None;
            }
        }
        o
    });
    let channel_args: Vec<String> = match &omero {
        Some(o) if c.channels.is_empty() && derived.is_none() && m.channels > 1 => {
            let active: Vec<String> = o
                .iter()
                .enumerate()
                .filter(|(i, ch)| ch.active && *i < m.channels)
                .map(|(i, _)| i.to_string())
                .collect();
            // The store's active channels, as many as the mode draws at
            // once (a store of 70 channels, all active, still renders).
            let most = match mode {
                RenderMode::Dvr => brickyard_render::params::MAX_DVR_CHANNELS,
                _ => brickyard_render::params::MAX_CHANNELS,
            };
            if active.len() > most {
                say_err!(
                    silent,
                    "note: the store has {} active channels; {mode_name} draws at most {most} at \
                     once: channels {}..{} shown (choose others with --channel)",
                    active.len(),
                    active[0],
                    active[most - 1],
                    mode_name = c.mode
                );
            }
            active.into_iter().take(most).collect()
        }
        _ => c.channels.clone(),
    };
    let mut styles = channel_args
        .iter()
        .map(|x| parse_channel(x, [lo as f32, hi as f32], m.channels, omero.as_deref()))
        .collect::<Result<Vec<_>>>()?;
    // A channel shown twice would be drawn twice (added up twice in mip and
    // slice); a second transfer function or level range for one channel
    // would silently replace the first.
    let mut per_channel_seen: Vec<(&str, usize, &String)> = vec![];
    for (st, arg) in styles.iter().zip(&channel_args) {
        once(&mut per_channel_seen, "channel", st.channel, arg)?;
    }
    for t in &c.channel_tfs {
        let (ch, spec) = t
            .split_once('=')
            .with_context(|| format!("channel-tf: expected C=PRESET or C=FILE, found {t:?}"))?;
        let ch: usize = ch
            .trim()
            .parse()
            .with_context(|| format!("channel-tf: {ch:?} in {t:?} is not a channel number"))?;
        once(&mut per_channel_seen, "channel-tf", ch, t)?;
        let Some(st) = styles.iter_mut().find(|s| s.channel == ch) else {
            if m.channels == 1 {
                bail!(
                    "channel-tf: transfer functions per channel are for dvr of several \
                     channels; this store has one channel: give its transfer function with --tf"
                );
            }
            bail!(
                "channel-tf: channel {ch} is not shown (give it with --channel, beside at least \
                 one other: one channel goes through --tf)"
            );
        };
        // A preset spans the channel's window, as --tf spans --window.
        st.tf = Some(transfer_function(spec, st.window, "channel-tf")?);
    }
    for t in &c.channel_levels {
        let (ch, range) = parse_channel_levels(t, info.levels.len())?;
        once(&mut per_channel_seen, "channel-levels", ch, t)?;
        let Some(st) = styles.iter_mut().find(|s| s.channel == ch) else {
            if m.channels == 1 {
                bail!(
                    "channel-levels: level ranges per channel are for dvr of several channels; \
                     this store has one channel: give its level with --level"
                );
            }
            bail!(
                "channel-levels: channel {ch} is not shown (give it with --channel, beside at \
                 least one other: one channel is drawn at --level)"
            );
        };
        st.levels = Some(range);
    }
    if derived.is_some() {
        // The derived volume has one channel. A bare `--channel C` only
        // names the channel it is computed from; with a colour it is also
        // how the derived channel is shown.
        if !c.channels.iter().any(|x| x.contains(':')) {
            styles.clear();
        }
        for st in &mut styles {
            st.channel = 0;
        }
    }
    if mode == RenderMode::Dvr {
        match styles.as_slice() {
            [] => {}
            [one] => {
                if one.tf.is_some() {
                    bail!("channel-tf: one channel in dvr goes through --tf");
                }
                if one.levels.is_some() {
                    bail!("channel-levels: one channel in dvr is drawn at --level (or the automatic level of detail); level ranges are for several channels");
                }
                scene.channel = one.channel;
                // One channel goes through --tf: a window given with it
                // (`--channel C:COLOR:LO,HI`) is that function's window,
                // and a colour is not used (said, not silently dropped).
                if let Some(arg) = channel_args.first().filter(|_| derived.is_none()) {
                    let parts: Vec<&str> = arg.splitn(3, ':').collect();
                    if parts.len() == 3 {
                        if c.window.is_some() {
                            bail!(
                                "channel: {arg:?} gives a window and so does --window: give it once"
                            );
                        }
                        if !labels {
                            tf = transfer_function(tf_name, one.window, "tf")?;
                        }
                    }
                    if parts.len() >= 2 {
                        say_err!(
                            silent,
                            "note: one channel in dvr is drawn through --tf ({tf_name}): the \
                             colour in --channel {arg} is not used (show two or more channels \
                             to composite them in their colours)"
                        );
                    }
                }
            }
            _ => {}
        }
    }
    // --tf draws one channel; several are drawn each in its own colour and
    // window (and in dvr with --channel-tf): said, not silently dropped
    // (not refused: the viewer's saved views give --tf with them).
    if styles.len() > 1 && c.tf.is_some() {
        say_err!(
            silent,
            "note: --tf is not used: {} channels are {} each in its own colour and window{}; \
             --tf is for one channel",
            styles.len(),
            if mode == RenderMode::Dvr {
                "composited"
            } else {
                "added up"
            },
            if mode == RenderMode::Dvr {
                " (or --channel-tf C=TF)"
            } else {
                ""
            }
        );
    }
    if mode != RenderMode::Dvr && !c.channel_tfs.is_empty() {
        bail!("channel-tf: transfer functions per channel are for dvr; mip and slice add channels up by colour and window");
    } else if mode != RenderMode::Dvr && !c.channel_levels.is_empty() {
        bail!("channel-levels: level ranges per channel are for dvr; mip and slice read every channel at one level");
    }
    // DVR of several channels composites them; one goes through --tf.
    let dvr_multi = mode == RenderMode::Dvr && styles.len() > 1;
    let mut cfg = cfg;
    let shown = if mode == RenderMode::Dvr && !dvr_multi {
        1
    } else {
        styles.len()
    };
    // The session and its back end; a default pool the device cannot
    // allocate is halved until it can (an explicit --pool is an error).
    let (mut s, pinned, mut backend) = loop {
        let mut s = match &derived {
            Some(d) => d.session(cfg.clone(), split.host, split.chunks, c.loader_threads)?,
            None => Session::open_with_budget(
                &c.store,
                cfg.clone(),
                split.host,
                split.chunks,
                c.loader_threads,
            )?,
        };
        s.loader()
            .set_read_delay(std::time::Duration::from_millis(c.read_delay_ms));
        // The coarsest levels stay resident: every sample finds data at some
        // level, whatever the pool's pressure.
        let pinned = match s.pin_coarsest(512, std::time::Duration::from_secs(120)) {
            Ok(p) => p,
            Err(e) if c.pool.is_some() => bail!("pool: {e} (--pool)"),
            Err(e) => {
                // The pool is a share of --memory: the host cache lends it
                // what it lacks where it can spare it, else the run says
                // which knob moves it.
                let Some(moved) = split.lend_pool(e.minimum_bytes) else {
                    bail!(
                        "pool: {e}; the pool is a share of --memory ({}): raise --memory ({}MiB \
                         holds it)",
                        human_bytes(split.total),
                        split.total_holding_pool(e.minimum_bytes) >> 20
                    );
                };
                say_err!(
                    silent,
                    "note: the pool takes {} of the host cache's share, to keep the coarsest \
                     level resident (pool {}, host cache {})",
                    human_bytes(moved),
                    human_bytes(split.pool),
                    human_bytes(split.host)
                );
                cfg.pool_bytes = split.pool;
                if c.upload.is_none() && batch {
                    cfg.upload_bytes_per_frame =
                        split.pool.min(device.upload_cap().unwrap_or(u64::MAX));
                }
                if c.requests.is_none() {
                    cfg.request_cap = requests_for(split.pool, split.host);
                }
                continue;
            }
        };
        match crate::backend::Backend::choose_on(
            &backend_choice,
            gpu_update,
            &mut s,
            shown,
            adapter,
        ) {
            Ok(b) => break (s, pinned, b),
            Err(e)
                if c.pool.is_none()
                    && cfg.pool_bytes >= 64 << 20
                    && crate::backend::device_out_of_memory(&e) =>
            {
                say_err!(
                    silent,
                    "note: the device cannot hold a brick pool of {}; trying {}",
                    human_bytes(cfg.pool_bytes),
                    human_bytes(cfg.pool_bytes / 2)
                );
                cfg.pool_bytes /= 2;
                split.pool = cfg.pool_bytes;
            }
            Err(e) => return Err(e),
        }
    };
    // The pool's true slot size (from here on: reports and estimates).
    let slot_bytes = (s.vm().pool_bytes() / s.vm().pool_slots().max(1)) as u64;
    if batch {
        s.set_batch(Some(std::time::Duration::from_secs(30)));
    }
    // Value ranges from the store's statistics: skip what the transfer
    // function hides without loading it.
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    if traversal == Traversal::Octree {
        // A device binds the octree's tables in one buffer: a depth whose
        // tables pass the device's limit for one is lowered (as one past
        // --memory is), and the run says so.
        let octree_depth = match backend.max_storage_binding() {
            Some(limit) => {
                let fit = fit_octree_to_device(octree_depth, scene.levels.len(), m.channels, limit);
                if let Some(n) = &fit.note {
                    say_err!(silent, "{n}");
                }
                fit.depth
            }
            None => octree_depth,
        };
        crate::backend::attach_octree(&mut scene, &mut s, octree_depth)?;
    }
    let lod = match c.level {
        Some(l) if l >= scene.levels.len() => {
            bail!("level: the store has {} levels", scene.levels.len())
        }
        Some(l) => Lod::Fixed(l),
        None => Lod::Auto { bias: c.lod_bias },
    };
    if let Some(n) = c.progressive {
        if mode != RenderMode::Dvr {
            bail!("progressive: sample accumulation draws DVR (--mode dvr)");
        }
        if dvr_multi {
            bail!("progressive: sample accumulation draws DVR of one channel; give one --channel");
        }
        if n == 0 || n > brickyard_render::savr::MAX_FRAMES {
            bail!(
                "progressive: N frames between 1 and {}, got {n}",
                brickyard_render::savr::MAX_FRAMES
            );
        }
        if c.no_early_termination && !matches!(backend, crate::backend::Backend::Cpu) {
            bail!("no-early-termination: the device's accumulation ends rays at an opacity of 0.99; use --backend cpu for --progressive without early termination");
        }
    }
    if !c.json {
        say!(
            silent,
            "rendering on {}{}",
            backend.describe(),
            match traversal {
                Traversal::Octree =>
                    format!(", DVR through a residency octree of depth {octree_depth}"),
                Traversal::PageTable => String::new(),
            }
        );
    }
    if !c.json && !c.quiet {
        say!(silent, "{}", split.describe());
        say!(
            silent,
            "pool: {} bricks of {}; levels {:?} kept resident ({} bricks, {})",
            s.vm().pool_slots(),
            human_bytes(slot_bytes),
            pinned.levels,
            pinned.bricks + pinned.flagged,
            human_bytes(pinned.bytes)
        );
    }
    let mut written = vec![];
    let views = c.turntable.unwrap_or(1).max(1);
    let opt = crate::frames::DriveOptions {
        batch,
        max_frames: c.max_frames,
        lod,
        band: None,
    };
    let levels = scene.levels.len();
    let base_bias = match lod {
        Lod::Auto { bias } => bias,
        Lod::Fixed(_) => 0.0,
    };
    // One budget for all views of a turntable: what did not fit one view
    // is unlikely to fit the next.
    let mut budget = brickyard_render::budget::LodBudget::new(base_bias, levels, false);
    // Data-parallel: this rank's region of the volume.
    let region = match (shared, share.as_deref_mut()) {
        (Some(Split::Data), Some(sh)) => {
            if !matches!(mode, RenderMode::Dvr | RenderMode::Mip)
                || (mode == RenderMode::Mip && styles.len() > 1)
            {
                bail!("distribute data: DVR (one or several channels) or MIP of one channel (sort-last compositing)");
            }
            if dvr_multi && c.backend == "gpu" {
                bail!("distribute data: several channels draw on the CPU of each rank (the device's channel mix takes no region); use --backend cpu");
            }
            if mode == RenderMode::Mip && !styles.is_empty() {
                // The channels' mix (--channel C:colour) draws every
                // sample of the ray; regions clip one channel through --tf.
                bail!("distribute data: MIP of the first channel through --tf (no --channel)");
            }
            if traversal != Traversal::PageTable {
                bail!("distribute data: --traversal page-table (regions clip the rays)");
            }
            let nb = m.dims.map(|d| d.div_ceil(c.brick));
            let ranges = scene.ranges.as_deref().and_then(|r| r.level(0));
            let by_data = weights != "uniform";
            let by_view = weights == "view";
            // DVR draws what the transfer function shows (a brick it
            // hides is crossed in one jump, a uniform one it shows is
            // sampled at every step); MIP draws bricks holding data (a
            // uniform one is crossed once the ray's maximum reaches it).
            // Accumulation samples every brick a ray crosses (a later
            // transfer function may show what this one hides).
            let accumulating = c.progressive.is_some();
            let drawn_dvr = |lo: f32, hi: f32| accumulating || tf.max_opacity(lo, hi) > 0.0;
            let drawn_mip = |lo: f32, hi: f32| lo < hi;
            let drawn: &dyn Fn(f32, f32) -> bool = match mode {
                RenderMode::Mip => &drawn_mip,
                _ => &drawn_dvr,
            };
            // Several channels: a brick weighs what its most costly channel
            // does (any visible channel makes the step sample them all).
            let tfs: Vec<(usize, brickyard_core::TransferFunction)> = match dvr_multi {
                true => styles.iter().map(|st| (st.channel, st.dvr_tf())).collect(),
                false => vec![],
            };
            let per_channel: Vec<Box<dyn Fn(f32, f32) -> bool + '_>> = tfs
                .iter()
                .map(|(_, t)| {
                    Box::new(move |lo: f32, hi: f32| accumulating || t.max_opacity(lo, hi) > 0.0)
                        as Box<dyn Fn(f32, f32) -> bool>
                })
                .collect();
            let one = crate::share::brick_weight(ranges, scene.channel, drawn);
            let channels: Vec<_> = tfs
                .iter()
                .zip(&per_channel)
                .map(|((ch, _), d)| crate::share::brick_weight(ranges, *ch, d.as_ref()))
                .collect();
            let data = |b: [u64; 3]| match channels.is_empty() {
                true => one(b),
                false => channels.iter().map(|w| w(b)).fold(0.0, f64::max),
            };
            // The view's rays per brick (a floor of a thousandth of the
            // mean, so that bricks no ray meets still count a little).
            let lengths = by_view.then(|| {
                let l = crate::share::ray_lengths(
                    &camera,
                    (n_views * w, h),
                    128,
                    (m.dims, spacing, c.brick),
                    nb,
                );
                let floor = 1e-3 * l.iter().sum::<f64>() / l.len().max(1) as f64;
                (l, floor)
            });
            let weight = |b: [u64; 3]| {
                let d = if by_data { data(b) } else { 1.0 };
                match &lengths {
                    Some((l, floor)) => {
                        d * (l[((b[0] * nb[1] + b[1]) * nb[2] + b[2]) as usize] + floor)
                    }
                    None => d,
                }
            };
            let boxes = sh.regions(nb, c.brick, spacing, &weight);
            // How the split shares out the bricks drawn.
            let holding = |b: [u64; 3]| (data(b) == 1.0) as u8 as f64;
            let counts: Vec<u64> = boxes.iter().map(|r| r.load(&holding) as u64).collect();
            say_text!(
                c.json,
                silent,
                "regions of {} ranks, split by {}: bricks drawn {:?}",
                boxes.len(),
                match (by_data, ranges.is_some()) {
                    (true, true) if by_view => "the view's rays and the store's statistics",
                    (true, false) if by_view => "the view's rays (no statistics)",
                    (true, true) => "the store's statistics",
                    (true, false) => "brick counts (no statistics)",
                    (false, _) => "brick counts (--region-weights uniform)",
                },
                counts
            );
            Some(
                boxes[sh.rank()]
                    .world(m.dims, spacing, c.brick)
                    .unwrap_or([[0.0; 3]; 2]),
            )
        }
        _ => None,
    };
    for v in 0..views {
        let cam = if c.turntable.is_some() {
            camera.turntable(views, v)
        } else {
            camera
        };
        let mut params = RenderParams::new(n_views * w, h, cam, tf.clone(), mode.clone());
        params.samples_per_voxel = samples_per_voxel;
        if n_views > 1 {
            let slices = matches!(mode, RenderMode::Slice { .. });
            let distance =
                brickyard_core::camera::length(brickyard_core::camera::sub(cam.target, cam.eye));
            params.views = Some(brickyard_core::views::Views {
                count: n_views,
                separation: match slices {
                    true => 0.0,
                    false => c.eye_separation.unwrap_or(distance / 30.0),
                },
                parallax: c.parallax.unwrap_or(1.0),
                spacing: c.spacing.unwrap_or(1.0) * scene.voxel(0),
                alone: None,
            });
        }
        if mode != RenderMode::Dvr || dvr_multi {
            params.channels = styles.clone();
        }
        params.reference_step = Some(scene.voxel(0));
        params.labels = labels;
        params.label_select = select.clone();
        params.traversal = traversal;
        params.early_termination = !(c.no_early_termination || data_split);
        if let Some(r) = region {
            params.clip = Some(Box::new(r));
            params.mip_values = mode == RenderMode::Mip;
        }
        params.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
        budget.view_changed();
        let (json, quiet) = (c.json, c.quiet);
        let mut on_frame = |fi: &crate::frames::FrameInfo| {
            let (f, st, fs) = (fi.f, &fi.f.stats, &fi.f.session);
            let read = fi.bytes_read;
            if json {
                say!(
                    silent,
                    "{}",
                    serde_json::json!({"view": v, "frame": fi.frame, "pass": if fi.pass {"requests"} else {"image"},
                            "ms": fi.ms, "completeness": st.completeness(), "lod_bias": fi.bias,
                            "samples": st.samples, "steps": st.steps, "octree_nodes": st.octree_nodes, "requests": fs.frame.requests.len(),
                            "bricks_in": fs.insert.inserted + fs.insert.flagged, "deferred": fs.insert.deferred,
                            "uploaded_bytes": fs.insert.bytes_uploaded, "bytes_read_total": read,
                            "render_ms": f.render_ms, "host_to_device_bytes": f.up, "device_to_host_bytes": f.down,
                            "resident": fs.frame.resident_bricks})
                );
            } else if !quiet {
                say!(silent,
                        "view {v} {} {:4}: {:6.2}% complete, {:8.1} ms, {:5} requests, {:5} bricks in, LOD bias {:+.1}, {} up, {} down",
                        if fi.pass { "pass " } else { "frame" },
                        fi.frame,
                        100.0 * st.completeness(),
                        fi.ms,
                        fs.frame.requests.len(),
                        fs.insert.inserted + fs.insert.flagged,
                        fi.bias,
                        human_bytes(f.up),
                        human_bytes(f.down)
                    );
            }
        };
        let drawn = match (shared, share.as_deref_mut()) {
            (Some(Split::Image), Some(sh)) => draw_bands(
                sh,
                v,
                (&mut backend, &mut s, &scene, &params),
                opt,
                &mut budget,
                &mut on_frame,
                c.progressive
                    .map(|n| (n, c.json || c.quiet || silent, split.samples)),
            ),
            _ => crate::frames::drive(
                &mut backend,
                &mut s,
                &scene,
                &params,
                opt,
                &mut budget,
                &mut on_frame,
            ),
        };
        // Shared: every rank says how its part went before the images meet.
        let out = match share.as_deref_mut() {
            Some(sh) if shared.is_some() => {
                let mine = drawn
                    .as_ref()
                    .map(|_| ())
                    .map_err(|e| anyhow::anyhow!("{e:#}"));
                sh.agree(mine)?;
                let out = drawn?;
                // How long each rank drew its part (the balance).
                let secs = sh.gather_times(out.seconds);
                say_text!(
                    c.json,
                    silent,
                    "view {v}: ranks drew their parts in {} s",
                    secs.iter()
                        .map(|t| format!("{t:.2}"))
                        .collect::<Vec<_>>()
                        .join(" / ")
                );
                out
            }
            _ => drawn?,
        };
        let read = s.loader().bytes_read();
        let mut failures = s.failures().to_vec();
        // Parts of the view with no data at any level (the coarsest
        // level's bricks could not be read either): no image of the view
        // can be made; an image with holes is not written as if it were.
        let holes = match failures.first() {
            Some(first) if out.unserved > 0 => Err(anyhow::anyhow!(
                "view {v}: {} brick(s) could not be loaded, the coarsest level's among them, so \
                 part of the view has no data at any level ({} samples); no image written. \
                 First: {}: {}",
                failures.len(),
                out.unserved,
                first.place(s.loader().geometry()),
                first.message
            )),
            _ => Ok(()),
        };
        let mut out = out;
        match share.as_deref_mut() {
            // Shared: holes in any rank's part fail every rank; the bricks
            // the others could not load and how their parts stopped are
            // reported by rank 0 with its own.
            Some(sh) if shared.is_some() => {
                sh.agree(holes)?;
                gather_outcome(sh, &mut out.stop, &mut out.completeness, &mut failures);
            }
            _ => holes?,
        }
        let why = match &out.stop {
            Some(Stop::Complete) => "complete".to_string(),
            Some(Stop::CompleteButFailed) => {
                format!("complete but for {} brick(s) {DEGRADED}", failures.len())
            }
            Some(Stop::NoProgress) => format!(
                "{STOPPED}{:.1}% complete: nothing more could arrive or be placed for several frames",
                100.0 * out.completeness
            ),
            None => format!(
                "{STOPPED}{:.1}% complete after --max-frames {}",
                100.0 * out.completeness,
                c.max_frames
            ),
        };
        let b = &out.budget;
        let detail = if b.extra() > 0.0 {
            let need = b
                .needed_at_base
                .map(|n| {
                    format!(
                        ", its first frame at full detail asked for about {}",
                        human_bytes(n as u64 * slot_bytes)
                    )
                })
                .unwrap_or_default();
            // A fixed level is said as the level drawn.
            let at = match lod {
                Lod::Fixed(l) => match b.apply(lod, scene.levels.len()) {
                    Lod::Fixed(m) => format!("level {m} (asked level {l})"),
                    Lod::Auto { .. } => unreachable!("a fixed level stays fixed"),
                },
                Lod::Auto { .. } => format!("LOD bias {:+.1} (asked {:+.1})", b.bias, b.base),
            };
            // (The resident coarsest levels take their part of it.)
            let pinned = s.vm().pinned_bricks() as u64 * slot_bytes;
            let beside = match pinned {
                0 => String::new(),
                p => format!(
                    ", {} of it beside the resident coarsest levels",
                    human_bytes((s.vm().pool_bytes() as u64).saturating_sub(p))
                ),
            };
            format!(
                " at {at}: the pool holds {}{beside}{need}",
                human_bytes(s.vm().pool_bytes() as u64)
            )
        } else {
            String::new()
        };
        let peak = crate::memory::peak_rss();
        if c.json {
            say!(
                silent,
                "{}",
                serde_json::json!({"view": v, "summary": true, "stop": stop_name(out.stop.as_ref()),
                    "completeness": out.completeness, "frames": out.frames, "seconds": out.seconds,
                    "lod_bias": b.bias, "lod_bias_asked": b.base,
                    "needed_bytes_at_full_detail": b.needed_at_base.map(|n| n as u64 * slot_bytes),
                    "pool_bytes": s.vm().pool_bytes(), "bytes_read_total": read,
                    "failed_bricks": failures.iter().map(|f| serde_json::json!({"key": {"level": f.key.level, "channel": f.key.channel, "brick": f.key.brick}, "voxels": f.voxels(s.loader().geometry()), "error": f.message})).collect::<Vec<_>>(),
                    "peak_rss_bytes": peak, "memory_budget_bytes": split.total})
            );
        }
        let mut detail_line = format!(
            "{why}{detail}; {} frames, {:.2} s, {} read",
            out.frames,
            out.seconds,
            human_bytes(read)
        );
        if !c.json {
            say!(silent, "view {v}: {detail_line}");
            for f in failures.iter().take(10) {
                say!(
                    silent,
                    "  could not load {}: {}",
                    f.place(s.loader().geometry()),
                    f.message
                );
            }
            if failures.len() > 10 {
                say!(silent, "  … and {} more", failures.len() - 10);
            }
        }
        for p in s.loader().take_stats_problems() {
            tell(silent, "warning", format!("brick statistics {p}"));
        }
        if let Some(d) = debug {
            // The debug image of the complete view: one more whole frame
            // at the level of detail the view ended with, counting.
            let mut dp = params.clone();
            dp.debug = Some(d);
            let f = backend.frame(&mut s, &scene, &dp, out.budget.apply(lod, levels))?;
            let mut img = f.image;
            let (most, sum) = img
                .rgba
                .iter()
                .fold((0.0f32, 0.0f64), |(m, t), p| (m.max(p[0]), t + p[0] as f64));
            let rays = (img.width as f64 * img.height as f64).max(1.0);
            let name = format!("{d:?}").to_lowercase();
            if c.json {
                say!(
                    silent,
                    "{}",
                    serde_json::json!({"view": v, "debug": name, "largest": most, "mean": sum / rays,
                        "octree_nodes": f.stats.octree_nodes, "steps": f.stats.steps, "samples": f.stats.samples})
                );
            } else {
                say!(
                    silent,
                    "view {v}: debug {name} per ray: largest {most} (white), mean {:.1}; {} octree nodes, {} steps, {} samples in the frame",
                    sum / rays,
                    f.stats.octree_nodes,
                    f.stats.steps,
                    f.stats.samples
                );
            }
            brickyard_render::cpu::false_colour(&mut img);
            let path = out_path(v);
            sink(&path, compose(img)?)?;
            written.push(format!("{}: debug {name}; {detail_line}", path.display()));
            continue;
        }
        let img = match c.progressive {
            // Image-parallel bands accumulated band by band.
            Some(n) if shared != Some(Split::Image) => {
                // The detail the view settled at: a fixed level the pool
                // could not hold fell back to a coarser one, which the
                // accumulation keeps (at the level asked for, the device
                // kept stand-ins it could never retake).
                let lod = b.apply(lod, scene.levels.len());
                let t = std::time::Instant::now();
                let acc = accumulate(
                    &mut backend,
                    &mut s,
                    &scene,
                    &params,
                    (lod, n, None),
                    split.samples,
                    (c.quiet || silent, c.json.then_some(v)),
                    &mut || {},
                );
                match share.as_deref_mut() {
                    // Data-parallel: every rank says how its region went.
                    Some(sh) if shared.is_some() => {
                        sh.agree(
                            acc.as_ref()
                                .map(|_| ())
                                .map_err(|e| anyhow::anyhow!("{e:#}")),
                        )?;
                        let secs = sh.gather_times(t.elapsed().as_secs_f64());
                        say_text!(
                            c.json,
                            silent,
                            "view {v}: ranks accumulated their regions in {} s",
                            secs.iter()
                                .map(|t| format!("{t:.2}"))
                                .collect::<Vec<_>>()
                                .join(" / ")
                        );
                        acc?.0
                    }
                    // Not even one frame's samples fit: the view as drawn
                    // (one frame, complete) is the image, said so; it had
                    // been drawn and thrown away for an error.
                    _ => match acc {
                        Err(e) if e.downcast_ref::<NoRoomToAccumulate>().is_some() => {
                            let line = format!(
                                "{e}; the image is the view's one frame, 1 of the {n} frames"
                            );
                            say_err!(silent, "note: {line}");
                            detail_line.push_str(&format!("; {line}"));
                            out.image
                        }
                        // The view's frames stopped short (--max-frames, or
                        // no progress), yet the accumulation's frames
                        // loaded the rest and left no stand-in: the image
                        // is complete, and said so (it ended with status 3).
                        Ok((img, true)) if matches!(out.stop, None | Some(Stop::NoProgress)) => {
                            let line = format!(
                                "complete after all: accumulating {n} frames loaded what the view's frames had not"
                            );
                            say_text!(c.json, silent, "view {v}: {line}");
                            detail_line = format!("{line}; the view's frames {detail_line}");
                            detail_line = detail_line.replacen(STOPPED, "had ended at ", 1);
                            img
                        }
                        r => r?.0,
                    },
                }
            }
            _ => out.image,
        };
        // Shared: the ranks' parts become one image on rank 0.
        let img = match (shared, share.as_deref_mut()) {
            (Some(Split::Image), Some(sh)) => sh.sum(img)?,
            (Some(Split::Data), Some(sh)) => {
                let (img, ms) =
                    sh.composite(img, mode == RenderMode::Mip, order_eye(&cam, extent))?;
                say_text!(
                    c.json,
                    silent,
                    "view {v}: composited {} ranks ({}) in {ms:.1} ms",
                    sh.size(),
                    if sh.size().is_power_of_two() {
                        "binary swap"
                    } else {
                        "direct send"
                    }
                );
                img.map(|mut i| {
                    if mode == RenderMode::Mip {
                        // The maxima of all regions through the transfer
                        // function, as one process maps its rays' maxima.
                        for p in &mut i.rgba {
                            *p = brickyard_render::optics::mip_color(&tf, p[3] > 0.0, p[0]);
                        }
                    }
                    i
                })
            }
            _ => Some(img),
        };
        let Some(img) = img else {
            continue;
        };
        let img = compose(img)?;
        let path = out_path(v);
        sink(&path, img)?;
        written.push(format!("{}: {detail_line}", path.display()));
    }
    if !c.json && !c.quiet {
        if let Some(p) = crate::memory::peak_rss() {
            say!(
                silent,
                "peak memory {} of a {} budget",
                human_bytes(p),
                human_bytes(split.total)
            );
        }
    }
    Ok(written)
}

/// `--traversal`, `--octree-depth`, `--debug` and what they allow: the
/// traversal, the octree's depth, the debug image and the back end to
/// open (`auto` becomes `cpu` for what only the CPU draws).
fn traversal_options(c: &RenderCmd) -> Result<TraversalChoice> {
    // (The octree's rays end at an opacity of 0.99 always: the flag was
    // dropped without a word.)
    if c.no_early_termination && c.traversal == "octree" {
        bail!(
            "no-early-termination: the octree traversal ends rays at an opacity of 0.99; use \
             --traversal page-table for rays without early termination"
        );
    }
    check_traversal(&TraversalFlags {
        gpu_update: c.gpu_update,
        traversal: &c.traversal,
        octree_depth: c.octree_depth,
        debug: c.debug.as_deref(),
        mode: Some(&c.mode),
        accumulation: c.progressive.map(|_| "--progressive"),
        backend: &c.backend,
    })
}

/// What a command was given of the flags that choose how DVR rays find
/// their bricks ([`check_traversal`]).
pub struct TraversalFlags<'a> {
    /// `--traversal`: octree or page-table.
    pub traversal: &'a str,
    pub octree_depth: Option<u32>,
    /// `--debug` (commands without it: `None`).
    pub debug: Option<&'a str>,
    /// `--mode` when it holds for everything drawn (`None`: the viewer,
    /// whose 3D view changes mode and whose slice views keep the page
    /// tables).
    pub mode: Option<&'a str>,
    /// The sample-accumulation flag given (`--progressive`,
    /// `--accumulate`), if any.
    pub accumulation: Option<&'a str>,
    /// `--backend`: auto, gpu or cpu.
    pub backend: &'a str,
    /// `--gpu-update`, if given.
    pub gpu_update: Option<crate::backend::GpuUpdate>,
}

/// What [`check_traversal`] allows of the flags.
pub struct TraversalChoice {
    pub traversal: Traversal,
    /// The octree's depth.
    pub depth: u32,
    pub debug: Option<DebugCounts>,
    /// The back end to open: `--backend`, or `cpu` for `auto` with a debug
    /// image (the caller says so).
    pub backend: String,
    /// Who decides the device's updates: `--gpu-update`, else the device,
    /// or the host for the octree.
    pub gpu_update: crate::backend::GpuUpdate,
}

/// The rules of `--traversal`, `--octree-depth` and `--debug`, shared by
/// `render` and `view`: the traversal, the octree's depth, the debug image
/// and the back end to open (`auto` becomes `cpu` for what only the CPU
/// draws; the caller says so).
pub fn check_traversal(f: &TraversalFlags) -> Result<TraversalChoice> {
    use crate::backend::GpuUpdate;
    let traversal: Traversal = f.traversal.parse().map_err(|e| anyhow::anyhow!("{e}"))?;
    let debug: Option<DebugCounts> = f
        .debug
        .map(str::parse)
        .transpose()
        .map_err(|e: String| anyhow::anyhow!("{e}"))?;
    let depth = f.octree_depth.unwrap_or(DEFAULT_DEPTH);
    if !(MIN_DEPTH..=MAX_DEPTH).contains(&depth) {
        bail!("octree-depth: expected {MIN_DEPTH} to {MAX_DEPTH}, got {depth}");
    }
    let octree = traversal == Traversal::Octree;
    if f.octree_depth.is_some() && !octree {
        bail!("octree-depth: only with --traversal octree");
    }
    if let Some(mode) = f.mode.filter(|m| *m != "dvr") {
        if octree {
            bail!(
                "traversal: the octree traversal draws DVR (--mode dvr); --mode {mode} draws through the page tables"
            );
        }
        if debug.is_some() {
            bail!("debug: debug images are drawn for DVR (--mode dvr)");
        }
    }
    if octree || debug.is_some() {
        let (flag, what, why) = match octree {
            true => (
                "traversal",
                "--traversal octree",
                "sample accumulation walks the page tables",
            ),
            false => (
                "debug",
                "--debug",
                "a debug image counts the work of one frame's rays",
            ),
        };
        if let Some(acc) = f.accumulation {
            bail!("{flag}: {what} and {acc} do not go together ({why})");
        }
    }
    let gpu_update = match (f.gpu_update, octree) {
        (Some(GpuUpdate::Device), true) => bail!(
            "gpu-update: the residency octree follows the host's virtual memory, so --traversal octree takes --gpu-update host (its default there)"
        ),
        (Some(u), _) => u,
        (None, true) => GpuUpdate::Host,
        (None, false) => GpuUpdate::Device,
    };
    let mut backend = f.backend.to_string();
    if debug.is_some() {
        match f.backend {
            "gpu" => bail!(
                "debug: --debug draws on the CPU only (the device counts nothing per pixel): use --backend cpu or auto"
            ),
            "auto" => backend = "cpu".into(),
            _ => {}
        }
    }
    Ok(TraversalChoice {
        traversal,
        depth,
        debug,
        backend,
        gpu_update,
    })
}

/// What `render` says when `--backend auto` became `cpu` for a debug
/// image ([`check_traversal`]).
pub fn auto_takes_cpu() -> String {
    "note: --debug draws on the CPU (the device counts nothing per pixel): --backend auto takes the CPU".into()
}

/// The octree traversal draws unshaded DVR: an error naming `--traversal`
/// when the transfer function `name` (`tf`) of a one-channel DVR shades.
pub fn check_octree_shading(
    traversal: Traversal,
    tf: &TransferFunction,
    name: &str,
    one_channel: bool,
) -> Result<()> {
    if traversal == Traversal::Octree && tf.shading.is_some() && one_channel {
        bail!(
            "traversal: the octree traversal draws unshaded DVR; the transfer function {name:?} has shading (turn it off or use --traversal page-table)"
        );
    }
    Ok(())
}

/// `--views`, `--stereo` and their companions: how many views and how
/// they are written (`None`: one view as it is).
fn view_layout(c: &RenderCmd) -> Result<(u32, Option<brickyard_render::views::Layout>)> {
    use brickyard_render::views::{Layout, Multiplex};
    let slices = c.mode == "slice";
    if !slices {
        for (flag, given) in [
            ("parallax", c.parallax.is_some()),
            ("spacing", c.spacing.is_some()),
        ] {
            if given {
                bail!("{flag}: super-slices only (--mode slice with --views N)");
            }
        }
    } else if c.eye_separation.is_some() || c.stereo.is_some() {
        bail!(
            "{}: slices take --views N (a super-slice) with --parallax and --spacing, not eyes",
            match c.stereo {
                Some(_) => "stereo",
                None => "eye-separation",
            }
        );
    }
    if let Some(d) = c.eye_separation {
        if !(d.is_finite() && d >= 0.0) {
            bail!("eye-separation: expected a distance of 0 or more, got {d}");
        }
    }
    if let Some(z) = c.spacing {
        if !(z.is_finite() && z >= 0.0) {
            bail!("spacing: expected 0 or more voxels, got {z}");
        }
    }
    if let Some(x) = c.parallax {
        if !x.is_finite() {
            bail!("parallax: expected a number of pixels, got {x}");
        }
    }
    match (&c.stereo, c.views) {
        (Some(_), Some(_)) => bail!("stereo: give --stereo (two views) or --views N, not both"),
        (Some(st), None) => {
            if c.multiplex.is_some() {
                bail!(
                    "multiplex: for --views N (2 to {}); --stereo says itself how its pair is \
                     written (sbs, tb or anaglyph)",
                    brickyard_core::views::MAX_VIEWS
                );
            }
            let layout = match st.as_str() {
                "sbs" => Layout::SideBySide,
                "tb" => Layout::TopBottom,
                "anaglyph" => Layout::Anaglyph,
                s => bail!("stereo: expected sbs, tb or anaglyph, found {s:?}"),
            };
            Ok((2, Some(layout)))
        }
        (None, Some(n)) => {
            if !(2..=brickyard_core::views::MAX_VIEWS).contains(&n) {
                bail!(
                    "views: expected 2 to {} views, got {n}",
                    brickyard_core::views::MAX_VIEWS
                );
            }
            let layout = match c.multiplex.as_deref() {
                None | Some("tiles") => Layout::Tiles,
                Some(file) => {
                    let m = Multiplex::from_file(std::path::Path::new(file))
                        .map_err(|e| anyhow::anyhow!("multiplex: {e}"))?;
                    if m.views != n {
                        bail!(
                            "multiplex: {file} describes {} views, --views asks for {n}",
                            m.views
                        );
                    }
                    Layout::Multiplex(m)
                }
            };
            Ok((n, Some(layout)))
        }
        (None, None) => {
            // (Each names what it does take: --stereo writes its pair its
            // own way, and slices have no eyes.)
            for (flag, given, with) in [
                ("multiplex", c.multiplex.is_some(), "with --views N"),
                (
                    "eye-separation",
                    c.eye_separation.is_some(),
                    "with --views N or --stereo",
                ),
                (
                    "parallax",
                    c.parallax.is_some(),
                    "with --views N (a super-slice)",
                ),
                (
                    "spacing",
                    c.spacing.is_some(),
                    "with --views N (a super-slice)",
                ),
            ] {
                if given {
                    bail!("{flag}: only {with}");
                }
            }
            Ok((1, None))
        }
    }
}

/// The device memory a sample store may take at least (the device
/// allocates a pixel's whole budget up front; pixels whose rays need more
/// stop at the rate it allows, and views whose rays need more for one run
/// are sampled at a coarser level). The pool's budget that its bricks
/// leave unused raises it, up to what one buffer of the device holds.
const DEVICE_STORE_BYTES: u64 = 512 << 20;

/// An accumulation that cannot keep even one frame's samples (the
/// caller may keep the view's image as drawn instead).
#[derive(Debug)]
struct NoRoomToAccumulate(String);

impl std::fmt::Display for NoRoomToAccumulate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for NoRoomToAccumulate {}

/// `--progressive N`: accumulation frames of the view (whose working set
/// the drive has just loaded) until `n` frames are blended and no stand-in
/// is left. The per-pixel store holds `n` whole rays of samples (on the
/// device: as many as one of its buffers holds).
///
/// `rows`: only these image rows (a band of an image-parallel render, on
/// the CPU); the image returned is then theirs. `between` runs after every
/// frame (rank 0 answers the other ranks there).
///
/// `bytes`: the share of --memory for the kept samples. The CPU's first
/// frame is sampled coarser where its runs could take more; after it,
/// fewer frames are drawn where the frames asked for would keep more. A
/// device whose memory is this process's (a software adapter) sizes its
/// store within it.
#[allow(clippy::too_many_arguments)]
fn accumulate(
    backend: &mut crate::backend::Backend,
    s: &mut Session,
    scene: &Scene,
    params: &RenderParams,
    (lod, n, rows): (Lod, u32, Option<std::ops::Range<u32>>),
    bytes: u64,
    (quiet, json): (bool, Option<u32>),
    between: &mut dyn FnMut(),
) -> Result<(brickyard_render::Image, bool)> {
    use crate::backend::Accumulating;
    // With --json (view `json`): a JSON line per frame and at the end on
    // stdout, the notes as text on stderr; else text lines on stdout.
    let text = !quiet && json.is_none();
    let note = |line: String| {
        if text {
            outln!("{line}");
        } else if !quiet {
            eprintln!("{line}");
        }
    };
    // The detail the view was drawn at (the accumulation may go coarser).
    let view_lod = lod;
    let steps = brickyard_render::savr::longest_run(scene, params, 0) as usize;
    backend.set_read_image(true);
    let mut budget = n as usize * steps;
    let cpu = matches!(backend, crate::backend::Backend::Cpu);
    // What the pool's budget leaves unused (a pool no larger than the
    // volume's bricks).
    let spare = {
        let vm = s.vm();
        vm.config()
            .pool_bytes
            .saturating_sub(vm.pool_slots() as u64 * vm.slot_bytes() as u64)
    };
    // The CPU's samples take their share and the pool's unused budget.
    let bytes = match cpu {
        true => bytes + spare,
        false => bytes,
    };
    let memory_for = format!(
        "the memory for them ({}: a quarter of --memory, and what the pool's budget leaves unused)",
        human_bytes(bytes)
    );
    if !cpu {
        // The device's store is allocated whole: at most this much (on a
        // software adapter, host memory: the samples' share of --memory,
        // or what the pool's budget leaves unused).
        let floor = match backend.device_in_host_memory() {
            true => bytes,
            false => DEVICE_STORE_BYTES,
        };
        let cap = brickyard_render::savr::device::DeviceAccumulation::budget_within(
            floor.max(spare),
            params.width,
            params.height,
            n,
            params.tf.shading.is_some(),
        );
        budget = budget.min(cap as usize);
    }
    let mut acc = match &rows {
        Some(r) => Accumulating::Cpu(brickyard_render::savr::Accumulation::rows(
            params.width,
            params.height,
            r.clone(),
            n,
            budget,
        )),
        None => Accumulating::new(backend, params, n, budget),
    };
    // A render shows the last image only: the frames before need no blend.
    acc.blend_last_only();
    // The CPU's first frame reserves room for every ray's whole run: at a
    // level whose runs fit the samples' share.
    let lod = match cpu {
        true => {
            use brickyard_render::savr::{first_frame_memory, lod_at_least};
            let band = rows.clone().unwrap_or(0..params.height);
            let at = |l: usize| first_frame_memory(scene, params, band.clone(), l);
            let from = lod_finest(lod);
            match (from..scene.levels.len()).find(|&l| at(l) <= bytes) {
                Some(l) if l == from => lod,
                Some(l) => {
                    let fit = lod_at_least(scene, params, lod, l);
                    // (A bias asked for may be coarse enough already.)
                    if fit != lod {
                        note(format!(
                            "progressive: the first frame's samples at level {from} may take {}, more than {memory_for}; accumulating at {} (more --memory, or a smaller image, keeps more detail)",
                            human_bytes(at(from)),
                            describe_lod(fit)
                        ));
                    }
                    fit
                }
                None => {
                    return Err(NoRoomToAccumulate(format!(
                        "progressive: the first frame's samples take up to {} even at the coarsest level, more than {memory_for}: raise --memory or draw a smaller image to accumulate",
                        human_bytes(at(scene.levels.len() - 1)),
                    ))
                    .into())
                }
            }
        }
        false => lod,
    };
    // A store too small for one run of the view's rays costs detail: say so.
    let kept = acc.budget() as u64;
    let within = brickyard_render::savr::lod_within(scene, params, lod, kept);
    match within {
        Some(fit) if fit != lod => note(format!(
            "progressive: a pixel keeps {kept} samples, fewer than one run of the longest ray takes at the level asked for ({}); accumulating at {} (a smaller image keeps more detail)",
            brickyard_render::savr::longest_run(scene, params, lod_finest(lod)),
            describe_lod(fit)
        )),
        None => bail!(
            "progressive: a pixel keeps {kept} samples (what one storage binding of the device holds for a row of the image), fewer than one run of the longest ray takes even at the coarsest level ({}): a smaller image, or --backend cpu",
            brickyard_render::savr::longest_run(scene, params, scene.levels.len() - 1)
        ),
        _ => {}
    }
    // A pixel begins run k only when k + 1 runs of its ray fit its store:
    // where the device's store is smaller than the frames asked for take
    // on the longest rays, those pixels stay at fewer frames (the CPU's
    // store grows: its budget is the frames' whole runs).
    let longest =
        brickyard_render::savr::longest_run(scene, params, lod_finest(within.unwrap_or(lod)));
    let fewest = (kept / longest.max(1)).min(n as u64) as u32;
    let t = std::time::Instant::now();
    let mut left = 0;
    let band = rows
        .as_ref()
        .map(|r| format!(" rows {}..{}", r.start, r.end))
        .unwrap_or_default();
    let mut prev = u64::MAX;
    let mut short = None;
    for frame in 1..=4 * n as usize + 64 {
        let f0 = std::time::Instant::now();
        let st = acc.frame(backend, s, scene, params, lod)?;
        // Stopped (Ctrl-C; a Python caller's KeyboardInterrupt) during
        // the frame: between frames, not after all of them.
        if scene.stopped() {
            return Err(crate::process::Interrupted.into());
        }
        between();
        left = st.stand_ins;
        short = st.incomplete;
        if text {
            outln!(
                "accumulate{band} {}/{}: {:8.1} ms, {} samples taken, {} stand-ins left, {} kept",
                acc.frames(),
                acc.target(),
                f0.elapsed().as_secs_f64() * 1e3,
                st.samples,
                st.stand_ins,
                human_bytes(acc.memory())
            );
        } else if let (Some(v), false) = (json, quiet) {
            outln!(
                "{}",
                serde_json::json!({"view": v, "accumulate": acc.frames(), "of": acc.target(),
                    "ms": f0.elapsed().as_secs_f64() * 1e3, "samples": st.samples,
                    "stand_ins": st.stand_ins, "kept_bytes": acc.memory()})
            );
        }
        // After the first frame: as many frames as the samples' share
        // holds (the next frame reserves their room).
        if frame == 1 {
            if let Some((t, asked)) = acc.fit_memory(bytes) {
                note(format!(
                    "progressive{band}: {n} frames would keep about {} of samples, more than {memory_for}; accumulating {t} (more --memory, or a smaller image, draws more)",
                    human_bytes(asked)
                ));
            }
        }
        if acc.complete() {
            // One frame at a coarser level than the view's adds no sample
            // and loses detail: the view as drawn is the image (it was
            // replaced by the coarser frame).
            if acc.target() <= 1 && lod != view_lod {
                return Err(NoRoomToAccumulate(format!(
                    "progressive{band}: one frame's samples fit at {}, coarser than the view \
                     drawn at {}, and no more: nothing to add (more --memory, or a smaller \
                     image, accumulates)",
                    describe_lod(lod),
                    describe_lod(view_lod)
                ))
                .into());
            }
            if let (Some(v), false) = (json, quiet) {
                outln!(
                    "{}",
                    serde_json::json!({"view": v, "accumulated": acc.target(), "asked": n,
                        "passes": frame, "seconds": t.elapsed().as_secs_f64()})
                );
            }
            if text {
                outln!(
                    "accumulated{band} {} frames in {frame} passes, {:.2} s{}",
                    match acc.target() {
                        t if t < n => format!("{t} of the {n}"),
                        _ => n.to_string(),
                    },
                    t.elapsed().as_secs_f64(),
                    match fewest < acc.target() {
                        true => format!(
                            "; a ray as long as the volume's diagonal ({longest} samples a run) keeps {fewest} of them in the {kept} samples of a pixel's store on the device (more --memory, or a smaller image, keeps more)"
                        ),
                        false => String::new(),
                    }
                );
            }
            // Every frame blended, no stand-in left: complete.
            return Ok((acc.image().clone(), true));
        }
        // Bricks that could not be loaded stay stand-ins for good: once
        // the frames asked for are blended and no more stand-ins go, the
        // image is as complete as it gets (drawn in part from coarser
        // data, which the view's line says).
        let stuck = left >= prev && acc.frames() >= acc.target();
        prev = left;
        if stuck && !s.failures().is_empty() {
            if text {
                outln!(
                    "accumulated{band} {n} frames in {frame} passes, {:.2} s, with {left} stand-in samples of bricks that could not be loaded",
                    t.elapsed().as_secs_f64()
                );
            } else if let (Some(v), false) = (json, quiet) {
                outln!(
                    "{}",
                    serde_json::json!({"view": v, "accumulated": n, "asked": n, "passes": frame,
                        "seconds": t.elapsed().as_secs_f64(), "stand_ins": left})
                );
            }
            return Ok((acc.image().clone(), false));
        }
    }
    if !s.failures().is_empty() {
        return Ok((acc.image().clone(), false));
    }
    // Every sample served at its level, yet pixels short of their blend:
    // the device cuts a blend longer than its loop limit (a software
    // device's 65535 iterations an invocation), frame after frame.
    if let (0, Some(k)) = (left, short.filter(|&k| k > 0)) {
        bail!(
            "progressive: {k} pixel(s) stayed short of their blend in every frame with all their samples at hand: the device cuts a blend this long; --backend cpu draws them, as do fewer frames (--progressive) or a lower --samples-per-voxel"
        )
    }
    bail!(
        "progressive: the accumulation did not complete ({left} stand-in samples left): the pool cannot hold the view's bricks"
    )
}

/// The threads reading bricks: 1 to 256 (each reads and decodes chunks
/// beside the others; more than a few per core only wait on each other).
pub fn check_loader_threads(n: usize) -> Result<()> {
    if !(1..=256).contains(&n) {
        bail!("loader-threads: expected 1 to 256 threads reading bricks, found {n}");
    }
    Ok(())
}

/// `lod` in words: "level 2", "a level-of-detail bias of +1.00".
fn describe_lod(lod: Lod) -> String {
    match lod {
        Lod::Fixed(l) => format!("level {l}"),
        Lod::Auto { bias } => format!("a level-of-detail bias of {bias:+.2}"),
    }
}

/// The finest level `lod` asks for anywhere (an automatic one: level 0,
/// near the eye).
fn lod_finest(lod: Lod) -> usize {
    match lod {
        Lod::Fixed(l) => l,
        Lod::Auto { .. } => 0,
    }
}

/// Where the eye is for the visibility order of regions: the camera's eye
/// (perspective), or far back along the view direction (orthographic:
/// every ray shares that direction).
fn order_eye(cam: &Camera, extent: [f64; 3]) -> [f64; 3] {
    match cam.projection {
        Projection::Orthographic { .. } => {
            let d = brickyard_core::camera::sub(cam.target, cam.eye);
            let len = brickyard_core::camera::length(d).max(1e-300);
            let far = 1e6 * extent.iter().cloned().fold(1.0, f64::max);
            [0, 1, 2].map(|a| cam.target[a] - d[a] / len * far)
        }
        _ => cam.eye,
    }
}

/// Shared: the buffers the ranks' images meet through, beyond a frame's
/// own images, in pixels of the images' share of the budget
/// ([`crate::memory::IMAGE_BYTES_PER_PIXEL`] each) for images of `pixels`
/// pixels. Direct send holds every rank's piece of this rank's span (a
/// whole image's worth) and their composite; binary swap at most half an
/// image received at once; rank 0 gathers the whole image; the sum of
/// image-parallel parts goes through pieces of at most 16 MiB. Rank 0's
/// (the most), on every rank: every rank's pool is the same.
fn exchange_pixels(shared: Option<Split>, ranks: usize, pixels: u64) -> u64 {
    const RGBA: u64 = 16;
    let bytes = match shared {
        _ if ranks < 2 => 0,
        Some(Split::Data) if ranks.is_power_of_two() => pixels * (RGBA / 2 + RGBA),
        Some(Split::Data) => pixels * RGBA + (pixels * RGBA).div_ceil(ranks as u64) + pixels * RGBA,
        Some(Split::Image) => (pixels * RGBA).min(16 << 20),
        None => 0,
    };
    bytes.div_ceil(crate::memory::IMAGE_BYTES_PER_PIXEL)
}

/// Shared: every rank's failed bricks and how its part of a view stopped,
/// gathered on rank 0 (collective): rank 0's `failures` gain the others'
/// (each brick once), its `stop` becomes the least complete of the ranks'
/// (stopped by --max-frames, then for want of progress, then complete but
/// for failed bricks) and its `completeness` the lowest. The other ranks'
/// are left as they are (they print nothing).
fn gather_outcome(
    sh: &mut dyn Share,
    stop: &mut Option<Stop>,
    completeness: &mut f64,
    failures: &mut Vec<brickyard_cache::loader::LoadFailure>,
) {
    let code = |s: &Option<Stop>| match s {
        Some(Stop::Complete) => 0u64,
        Some(Stop::CompleteButFailed) => 1,
        Some(Stop::NoProgress) => 2,
        None => 3,
    };
    let mine = serde_json::json!({
        "stop": code(stop),
        "completeness": *completeness,
        "failures": failures.iter().map(|f| serde_json::json!([
            f.key.level, f.key.channel, f.key.brick, f.io, f.message
        ])).collect::<Vec<_>>(),
    });
    let all = sh.gather_text(mine.to_string());
    let mut worst = code(stop);
    for (r, text) in all.iter().enumerate().skip(1) {
        let Ok(j) = serde_json::from_str::<serde_json::Value>(text) else {
            // (Cannot happen: every rank sends what it made above.)
            eprintln!("warning: rank {r}: unreadable report of its part: {text:?}");
            continue;
        };
        worst = worst.max(j["stop"].as_u64().unwrap_or(3));
        if let Some(c) = j["completeness"].as_f64() {
            *completeness = completeness.min(c);
        }
        for f in j["failures"].as_array().into_iter().flatten() {
            let brick: Option<Vec<u32>> = f[2]
                .as_array()
                .map(|b| b.iter().map(|x| x.as_u64().unwrap_or(0) as u32).collect());
            let key = brickyard_cache::brick::BrickKey {
                level: f[0].as_u64().unwrap_or(0) as u8,
                channel: f[1].as_u64().unwrap_or(0) as u16,
                brick: match brick.as_deref() {
                    Some(&[z, y, x]) => [z, y, x],
                    _ => [0; 3],
                },
            };
            if failures.iter().all(|g| g.key != key) {
                failures.push(brickyard_cache::loader::LoadFailure {
                    key,
                    message: f[4].as_str().unwrap_or_default().to_string(),
                    io: f[3].as_bool().unwrap_or(false),
                });
            }
        }
    }
    if !all.is_empty() {
        *stop = match worst {
            0 => Some(Stop::Complete),
            1 => Some(Stop::CompleteButFailed),
            2 => Some(Stop::NoProgress),
            _ => None,
        };
    }
}

/// Image-parallel: draw bands of tile rows of view `v` as `share` hands
/// them out, each until it is complete, into one image (the other pixels
/// transparent). Rank 0 answers the others between its frames.
/// `progressive`: `(N, quiet)`, each band then accumulates `N` frames once
/// its plain frames are complete, and its pixels are the accumulation's.
#[allow(clippy::too_many_arguments)]
fn draw_bands(
    share: &mut dyn Share,
    v: u32,
    (backend, s, scene, params): (
        &mut crate::backend::Backend,
        &mut Session,
        &Scene,
        &RenderParams,
    ),
    opt: crate::frames::DriveOptions,
    budget: &mut brickyard_render::budget::LodBudget,
    on_frame: &mut dyn FnMut(&crate::frames::FrameInfo),
    progressive: Option<(u32, bool, u64)>,
) -> Result<crate::frames::Outcome> {
    use brickyard_render::cpu::Tiles;
    let t0 = std::time::Instant::now();
    let (w, h) = (params.width, params.height);
    let rows = Tiles::rows_of(h);
    let mut image = brickyard_render::Image::new(w, h);
    let (mut frames, mut completeness, mut stop) = (0, 1.0f64, Some(Stop::Complete));
    let mut unserved = 0;
    let r = (|| -> Result<()> {
        while let Some((a, b)) = share.next_band(v, rows)? {
            let o = crate::frames::drive(
                backend,
                s,
                scene,
                params,
                crate::frames::DriveOptions {
                    band: Some((a, b)),
                    ..opt
                },
                budget,
                |fi| {
                    on_frame(fi);
                    share.serve();
                },
            )?;
            let px = Tiles::pixel_rows(h, a..b);
            let span = px.start as usize * w as usize..px.end as usize * w as usize;
            match progressive {
                Some((n, quiet, samples)) => {
                    let lod = o.budget.apply(opt.lod, scene.levels.len());
                    let band = accumulate(
                        backend,
                        s,
                        scene,
                        params,
                        (lod, n, Some(px)),
                        samples,
                        (quiet, None),
                        &mut || share.serve(),
                    )?
                    .0;
                    image.rgba[span].copy_from_slice(&band.rgba);
                }
                None => image.rgba[span.clone()].copy_from_slice(&o.image.rgba[span]),
            }
            frames += o.frames;
            completeness = completeness.min(o.completeness);
            unserved += o.unserved;
            if o.stop != Some(Stop::Complete) {
                stop = o.stop;
            }
        }
        Ok(())
    })();
    if r.is_err() {
        // No more bands for this rank; rank 0 still answers the others.
        share.stop_asking(v);
    }
    r?;
    Ok(crate::frames::Outcome {
        image,
        frames,
        stop,
        budget: budget.clone(),
        completeness,
        unserved,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An octree whose device tables pass the device's limit for one
    /// buffer is drawn through the deepest that fits, and said so.
    #[test]
    fn an_octree_too_deep_for_the_device_is_lowered_to_fit() {
        use brickyard_render::octree::Octree;
        let limit = 128u64 << 20;
        let fit = fit_octree_to_device(7, 3, 1, limit);
        assert!(Octree::device_table_bytes(7, 3, 1) > limit);
        assert_eq!(fit.depth, 6);
        assert!(fit.bytes <= limit);
        let note = fit.note.unwrap();
        assert!(
            note.contains("past its limit of 128.0 MiB") && note.contains("depth 6"),
            "{note}"
        );
        // One that fits is left as asked, without a note.
        let fit = fit_octree_to_device(5, 3, 1, limit);
        assert_eq!((fit.depth, fit.note), (5, None));
    }
}
