//! A WGSL module with several entry points sharing one bind-group layout.

use crate::context::Gpu;

/// How a binding is used by the module's entry points.
#[derive(Debug, Clone, Copy)]
pub enum Binding {
    Uniform,
    Read,
    ReadWrite,
    /// A 3D texture read with `textureLoad` (any float format, filterable
    /// or not).
    Texture3d,
}

/// The pipelines of one WGSL module, all with the same bind-group layout
/// (bindings `0..n` of group 0).
pub struct Kernel {
    layout: wgpu::BindGroupLayout,
    pipelines: Vec<(String, wgpu::ComputePipeline)>,
}

impl Kernel {
    pub fn new(
        gpu: &Gpu,
        label: &str,
        source: &str,
        entries: &[&str],
        bindings: &[Binding],
    ) -> Kernel {
        let dev = &gpu.device;
        let module = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let layout_entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: match b {
                    Binding::Texture3d => wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D3,
                        multisampled: false,
                    },
                    _ => wgpu::BindingType::Buffer {
                        ty: match b {
                            Binding::Uniform => wgpu::BufferBindingType::Uniform,
                            Binding::Read => wgpu::BufferBindingType::Storage { read_only: true },
                            _ => wgpu::BufferBindingType::Storage { read_only: false },
                        },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                },
                count: None,
            })
            .collect();
        let layout = dev.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(label),
            entries: &layout_entries,
        });
        let pl = dev.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipelines = entries
            .iter()
            .map(|e| {
                let p = dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(e),
                    layout: Some(&pl),
                    module: &module,
                    entry_point: Some(e),
                    compilation_options: Default::default(),
                    cache: None,
                });
                (e.to_string(), p)
            })
            .collect();
        Kernel { layout, pipelines }
    }

    /// A bind group with `buffers` at bindings `0, 1, …`.
    pub fn bind(&self, gpu: &Gpu, buffers: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        let r: Vec<wgpu::BindingResource> = buffers.iter().map(|b| b.as_entire_binding()).collect();
        self.bind_resources(gpu, r)
    }

    /// A bind group with `resources` at bindings `0, 1, …`.
    pub fn bind_resources(
        &self,
        gpu: &Gpu,
        resources: Vec<wgpu::BindingResource>,
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .into_iter()
            .enumerate()
            .map(|(i, resource)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource,
            })
            .collect();
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.layout,
            entries: &entries,
        })
    }

    /// Record a dispatch of entry point `entry` with `groups` workgroups.
    pub fn dispatch(
        &self,
        enc: &mut wgpu::CommandEncoder,
        entry: &str,
        bind: &wgpu::BindGroup,
        groups: [u32; 3],
    ) {
        let (_, p) = self
            .pipelines
            .iter()
            .find(|(n, _)| n == entry)
            .unwrap_or_else(|| panic!("no entry point {entry}"));
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(entry),
            timestamp_writes: None,
        });
        pass.set_pipeline(p);
        pass.set_bind_group(0, bind, &[]);
        pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
    }
}
