//! The host's part of a frame when the device decides updates: what the
//! loader delivered goes to the device (a session over a store: not in the
//! browser build).

use brickyard_cache::brick::BrickContent;
use brickyard_cache::brick::BrickKey;
use brickyard_cache::cells::cell_ranges_of_bytes;
use brickyard_cache::session::Session;
use brickyard_core::vm::PageEntry;
use brickyard_gpu::context::{Gpu, GpuError};
use brickyard_gpu::update::{DeviceCache, Item, UpdateCounts, NONE};
use brickyard_gpu::vm::DeviceVm;

/// What one [`update_on_device`] did.
#[derive(Debug, Clone, Default)]
pub struct DeviceUpdate {
    /// Bricks the loader delivered, and queued requests it cancelled.
    pub delivered: usize,
    pub cancelled: usize,
    /// The requests sent to the loader: the device's list without the
    /// bricks already here, capped (see `Session::exchange`).
    pub requested: Vec<BrickKey>,
    /// Data bricks written, empty or constant bricks sent.
    pub inserted: usize,
    pub flagged: usize,
    /// Data bricks ready that found no free slot (every slot in use this
    /// frame); they wait.
    pub deferred: usize,
    /// Host→device bytes (bricks as texels, 48 bytes of key per brick) and
    /// device→host bytes (the counts and 4 bytes per slot asked for).
    pub up: u64,
    pub down: u64,
    pub counts: UpdateCounts,
}

/// The host's part of a frame when the device decides updates
/// ([`DeviceCache`]), after [`GpuRenderer::render_with`]: hand the
/// device's request list (`list`, most wanted first) to the loader; ask the
/// device for as many pool slots as data bricks are ready, within the
/// upload budget; write those bricks there; send every ready brick's key
/// and kind, which the device references. Queued on the device; nothing
/// waits for I/O.
pub fn update_on_device(
    gpu: &Gpu,
    dvm: &mut DeviceVm,
    cache: &mut DeviceCache,
    s: &mut Session,
    frame: u32,
    list: &[BrickKey],
) -> Result<DeviceUpdate, GpuError> {
    let (delivered, cancelled, requested) = s.exchange(list);
    // Every empty or constant brick goes; data bricks up to the upload
    // budget, oldest first.
    let budget = s.vm().config().upload_bytes_per_frame;
    let mut bytes = 0u64;
    let mut data = vec![];
    for (i, b) in s.waiting().iter().enumerate() {
        if let BrickContent::Data(v) = &b.content {
            if bytes + v.len() as u64 > budget {
                break;
            }
            bytes += v.len() as u64;
            data.push(i);
        }
    }
    let slots = cache.end_frame(gpu, dvm, frame, data.len())?;
    // Slots run out at the end of the list, if at all.
    let mut given = data
        .iter()
        .zip(&slots)
        .filter(|(_, &slot)| slot != NONE)
        .map(|(&i, &slot)| (i, slot))
        .peekable();
    let mut done = vec![false; s.waiting().len()];
    let mut items = vec![];
    // The bricks given slots, written into the pool together.
    let mut writes: Vec<(u32, &[u8])> = vec![];
    let mut cells_of: Vec<Vec<[f32; 2]>> = vec![];
    let dtype = s.vm().dtype();
    let (brick, apron, padded) = (
        s.vm().config().brick,
        s.vm().config().apron,
        s.vm().padded(),
    );
    for (i, b) in s.waiting().iter().enumerate() {
        let item = match &b.content {
            BrickContent::Empty => Item::empty(b.key),
            BrickContent::Constant(v) => {
                Item::constant(b.key, PageEntry::constant_bits_of(dtype, *v))
            }
            BrickContent::Data(v) => match given.peek() {
                Some(&(j, slot)) if j == i => {
                    given.next();
                    let cells = cell_ranges_of_bytes(dtype, v, padded, brick, apron);
                    writes.push((slot, &v[..]));
                    cells_of.push(cells);
                    Item::data(b.key, slot)
                }
                _ => continue,
            },
        };
        done[i] = true;
        items.push(item);
    }
    let writes: Vec<brickyard_gpu::pool::BrickWrite> = writes
        .iter()
        .zip(&cells_of)
        .map(|(&(s, v), c)| (s, v, &c[..]))
        .collect();
    dvm.pool.write_many(gpu, &writes);
    let mut up = dvm.pool.take_uploaded();
    up += cache.reference(gpu, dvm, frame, &items);
    s.hand_over(&done);
    let inserted = items.iter().filter(|i| i.kind == 1).count();
    Ok(DeviceUpdate {
        delivered,
        cancelled,
        requested,
        inserted,
        flagged: items.len() - inserted,
        deferred: data.len() - inserted,
        up,
        down: 32 + 4 * slots.len() as u64,
        counts: cache.counts(),
    })
}
