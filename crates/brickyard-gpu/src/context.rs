//! The device: adapter choice, limits and features, and the small helpers
//! every kernel uses (buffers, read-back).

use std::fmt;

/// Errors of the GPU back end.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (looked at: {looked}); install a Vulkan driver \
         (on Debian or Ubuntu, Mesa's software one: `apt-get install mesa-vulkan-drivers`) \
         or use the CPU back end (`--backend cpu`)"
    )]
    NoAdapter { looked: String },
    #[error("the adapter {adapter} refused to open a device: {source}")]
    Device {
        adapter: String,
        source: wgpu::RequestDeviceError,
    },
    #[error("reading back {what} from the device failed: {reason}")]
    ReadBack { what: String, reason: String },
    #[error("{what}: {got} exceeds the device's limit of {limit}")]
    Limit { what: String, got: u64, limit: u64 },
    #[error("the device could not allocate {what} ({bytes} bytes): {reason}; give it a smaller budget (--pool or --memory)")]
    OutOfMemory {
        what: String,
        bytes: u64,
        reason: String,
    },
}

/// Which adapters [`Gpu::new`] accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterChoice {
    /// The best one: discrete, then integrated, then virtual, then
    /// software (CPU) adapters.
    Best,
    /// Only a software adapter (Mesa's lavapipe, WARP): for tests that must
    /// run the same everywhere.
    Software,
}

/// An open device with its queue and what the back end chose.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    /// 3D textures in `R16Unorm` can be sampled with filtering
    /// (`TEXTURE_FORMAT_16BIT_NORM`; no browser has it).
    pub r16_unorm: bool,
    pub limits: wgpu::Limits,
}

impl fmt::Debug for Gpu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.describe())
    }
}

/// Lower is preferred.
fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

impl Gpu {
    /// Open the best adapter of the native back ends (Vulkan, Metal, DX12).
    /// `WGPU_ADAPTER_NAME` (a substring of the adapter's name) narrows the
    /// choice, as in every wgpu program.
    pub fn new(choice: AdapterChoice) -> Result<Gpu, GpuError> {
        Gpu::new_nth(choice, 0)
    }

    /// [`Gpu::new`] on adapter `n` modulo the count of the adapters of the
    /// preferred kind (several discrete GPUs, say) in the order the back
    /// ends list them: one process per device in a node (`n` = the MPI
    /// rank). With one adapter every `n` opens it (a device of its own).
    pub fn new_nth(choice: AdapterChoice, n: usize) -> Result<Gpu, GpuError> {
        pollster::block_on(Self::open(Self::pick(choice, n)?))
    }

    /// The adapter [`Gpu::new_nth`] would open, without opening a device
    /// on it (the driver is loaded, no device memory is taken): what a
    /// caller needs to know before it budgets memory for one.
    pub fn adapter_info(choice: AdapterChoice, n: usize) -> Result<wgpu::AdapterInfo, GpuError> {
        Self::pick(choice, n).map(|a| a.get_info())
    }

    fn pick(choice: AdapterChoice, n: usize) -> Result<wgpu::Adapter, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY));
        let looked = if adapters.is_empty() {
            "no adapter on Vulkan, Metal or DX12".to_string()
        } else {
            adapters
                .iter()
                .map(|a| {
                    let i = a.get_info();
                    format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
                })
                .collect::<Vec<_>>()
                .join(", ")
        };
        let wanted = std::env::var("WGPU_ADAPTER_NAME")
            .ok()
            .map(|s| s.to_lowercase());
        let accepted: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| {
                let i = a.get_info();
                let software = i.device_type == wgpu::DeviceType::Cpu;
                (choice == AdapterChoice::Best || software)
                    && wanted
                        .as_ref()
                        .is_none_or(|w| i.name.to_lowercase().contains(w))
            })
            .collect();
        let best = accepted
            .iter()
            .map(|a| rank(a.get_info().device_type))
            .min();
        let mut preferred: Vec<wgpu::Adapter> = accepted
            .into_iter()
            .filter(|a| Some(rank(a.get_info().device_type)) == best)
            .collect();
        if preferred.is_empty() {
            return Err(GpuError::NoAdapter { looked });
        }
        let count = preferred.len();
        Ok(preferred.swap_remove(n % count))
    }

    /// Open a device on `adapter`: the WebGPU defaults, raised only where
    /// volumes need more (buffer and binding sizes for brick pools and page
    /// tables, 3D textures) and the adapter allows; `R16Unorm` textures
    /// where the adapter has them.
    async fn open(adapter: wgpu::Adapter) -> Result<Gpu, GpuError> {
        let info = adapter.get_info();
        let have = adapter.limits();
        let mut limits = wgpu::Limits::defaults();
        limits.max_buffer_size = have.max_buffer_size;
        limits.max_storage_buffer_binding_size = have.max_storage_buffer_binding_size;
        limits.max_texture_dimension_3d = have.max_texture_dimension_3d;
        let r16_unorm = adapter
            .features()
            .contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM);
        let features = if r16_unorm {
            wgpu::Features::TEXTURE_FORMAT_16BIT_NORM
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("brickyard"),
                required_features: features,
                required_limits: limits.clone(),
                experimental_features: wgpu::ExperimentalFeatures::disabled(),
                memory_hints: wgpu::MemoryHints::Performance,
                trace: wgpu::Trace::Off,
            })
            .await
            .map_err(|source| GpuError::Device {
                adapter: info.name.clone(),
                source,
            })?;
        Ok(Gpu {
            device,
            queue,
            info,
            r16_unorm,
            limits,
        })
    }

    /// The browser's WebGPU device (`wasm32`): the adapter the browser
    /// offers, with the WebGPU default limits raised only where the
    /// adapter allows (buffer and binding sizes, 3D texture edge), as
    /// [`Gpu::new`] does natively. Asynchronous: a page cannot block.
    #[cfg(target_arch = "wasm32")]
    pub async fn new_web() -> Result<Gpu, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::BROWSER_WEBGPU;
        let instance = wgpu::Instance::new(desc);
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions::default())
            .await
            .map_err(|e| GpuError::NoAdapter {
                looked: format!("WebGPU (navigator.gpu): {e}"),
            })?;
        Self::open(adapter).await
    }

    /// The most bytes one storage binding can take: the binding limit, and
    /// no more than one buffer holds.
    pub fn max_storage_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// A software adapter (Mesa's lavapipe, WARP): its device memory is
    /// this process's memory.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// One line for logs and reports: name, kind and back end.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?}, driver {})",
            self.info.name, self.info.device_type, self.info.backend, self.info.driver_info
        )
    }

    /// A storage buffer holding `data`, also usable as a copy source and
    /// destination.
    pub fn storage_buffer<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        // Zero-sized bindings are invalid: keep at least 4 bytes.
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let pad = [0u8; 4];
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: if bytes.is_empty() { &pad } else { bytes },
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// An uninitialised (zeroed) storage buffer of `bytes` bytes.
    pub fn storage_buffer_zeroed(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(4).next_multiple_of(4),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// A uniform buffer holding `data`.
    pub fn uniform_buffer<T: bytemuck::Pod>(&self, label: &str, data: &T) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::bytes_of(data),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// Copy `bytes` bytes from the start of `src` to the host (waits for
    /// the device).
    pub fn read_back(
        &self,
        what: &str,
        src: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<u8>, GpuError> {
        pollster::block_on(self.read_back_async(what, src, bytes))
    }

    /// [`read_back`](Self::read_back) without blocking: in the browser the
    /// mapping completes on the page's event loop while this waits;
    /// natively the device is polled until it has, so the future is
    /// ready when first polled.
    pub async fn read_back_async(
        &self,
        what: &str,
        src: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<u8>, GpuError> {
        let size = bytes.max(4).next_multiple_of(4);
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read-back"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, size);
        self.queue.submit([enc.finish()]);
        let (tx, rx) = futures_channel::oneshot::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        let fail = |reason: String| GpuError::ReadBack {
            what: what.to_string(),
            reason,
        };
        #[cfg(not(target_arch = "wasm32"))]
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| fail(e.to_string()))?;
        rx.await
            .map_err(|e| fail(e.to_string()))?
            .map_err(|e| fail(e.to_string()))?;
        let view = staging
            .get_mapped_range(..)
            .map_err(|e| fail(format!("{e:?}")))?;
        let out = view[..bytes as usize].to_vec();
        drop(view);
        staging.unmap();
        Ok(out)
    }

    /// [`read_back_async`](Self::read_back_async) as `u32` words.
    pub async fn read_u32_async(
        &self,
        what: &str,
        src: &wgpu::Buffer,
        words: usize,
    ) -> Result<Vec<u32>, GpuError> {
        let b = self.read_back_async(what, src, words as u64 * 4).await?;
        Ok(bytemuck::pod_collect_to_vec(&b))
    }

    /// [`read_back`](Self::read_back) as `u32` words.
    pub fn read_u32(
        &self,
        what: &str,
        src: &wgpu::Buffer,
        words: usize,
    ) -> Result<Vec<u32>, GpuError> {
        let b = self.read_back(what, src, words as u64 * 4)?;
        Ok(bytemuck::pod_collect_to_vec(&b))
    }
}

/// The device for tests. A missing adapter fails the test, unless
/// `BRICKYARD_SKIP_GPU=1` says explicitly to skip (then `None`);
/// `BRICKYARD_REQUIRE_GPU=1` (set in CI) overrides that opt-out.
pub fn test_gpu() -> Option<Gpu> {
    let flag = |k: &str| std::env::var(k).is_ok_and(|v| v == "1");
    match Gpu::new(AdapterChoice::Best) {
        Ok(g) => {
            eprintln!("GPU tests on {}", g.describe());
            Some(g)
        }
        Err(e) if flag("BRICKYARD_SKIP_GPU") && !flag("BRICKYARD_REQUIRE_GPU") => {
            eprintln!("skipped (BRICKYARD_SKIP_GPU=1): {e}");
            None
        }
        Err(e) => panic!("{e} (set BRICKYARD_SKIP_GPU=1 to skip GPU tests explicitly)"),
    }
}
