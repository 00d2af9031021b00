//! Bricks as the cache sees them: their key, their content (with apron) and
//! the geometry of the engine's brick grid.
//!
//! The engine's brick size is independent of the store's chunking: a brick
//! may span several Zarr chunks or be a part of one.

use brickyard_core::{DType, Dims3};
use std::sync::Arc;

/// Most levels a [`BrickKey`] can address (5 bits).
pub const MAX_LEVELS: usize = 1 << 5;
/// Most channels a [`BrickKey`] can address (11 bits).
pub const MAX_CHANNELS: usize = 1 << 11;
/// Most bricks per axis a [`BrickKey`] can address (16 bits).
pub const MAX_BRICKS_PER_AXIS: u64 = 1 << 16;

/// The address of one brick: pyramid level (0 = full resolution), channel,
/// and brick index `[z, y, x]` in the level's brick grid.
///
/// The derived order (level, channel, z, y, x) is the order of
/// [`BrickKey::pack`]ed values.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BrickKey {
    pub level: u8,
    pub channel: u16,
    pub brick: [u32; 3],
}

impl BrickKey {
    pub fn new(level: u8, channel: u16, brick: [u32; 3]) -> Self {
        BrickKey {
            level,
            channel,
            brick,
        }
    }

    /// Whether every field fits the packed layout.
    pub fn fits(&self) -> bool {
        (self.level as usize) < MAX_LEVELS
            && (self.channel as usize) < MAX_CHANNELS
            && self.brick.iter().all(|&b| (b as u64) < MAX_BRICKS_PER_AXIS)
    }

    /// Pack into 64 bits, most significant first:
    ///
    /// | bits  | 63–59 | 58–48   | 47–32   | 31–16   | 15–0    |
    /// |-------|-------|---------|---------|---------|---------|
    /// | field | level | channel | brick z | brick y | brick x |
    ///
    /// (5 + 11 + 3 × 16 bits.) Packed values sort like the keys.
    ///
    /// # Panics
    /// When a field does not fit ([`BrickKey::fits`]); the loader refuses
    /// volumes whose keys would not fit, so this only catches misuse.
    pub fn pack(&self) -> u64 {
        assert!(self.fits(), "{self:?} does not fit the packed brick key");
        ((self.level as u64) << 59)
            | ((self.channel as u64) << 48)
            | ((self.brick[0] as u64) << 32)
            | ((self.brick[1] as u64) << 16)
            | self.brick[2] as u64
    }

    /// Inverse of [`BrickKey::pack`] (every `u64` is a valid packed key).
    pub fn unpack(v: u64) -> Self {
        BrickKey {
            level: (v >> 59) as u8,
            channel: ((v >> 48) & 0x7ff) as u16,
            brick: [
                ((v >> 32) & 0xffff) as u32,
                ((v >> 16) & 0xffff) as u32,
                (v & 0xffff) as u32,
            ],
        }
    }
}

/// What a loaded brick holds.
#[derive(Clone, Debug, PartialEq)]
pub enum BrickContent {
    /// Every voxel of the padded brick is 0 (the fill value).
    Empty,
    /// Every voxel of the padded brick has this value (never 0, never NaN).
    Constant(f64),
    /// The padded brick: `(b + 2a)` voxels per axis, `[z, y, x]` order (x
    /// fastest), native-endian voxels of the volume's data type. Voxel
    /// `(i, j, k)` of the buffer is voxel `origin − a + (i, j, k)` of the
    /// level, coordinates clamped to the level (the border voxel is
    /// replicated outside the volume).
    Data(Arc<[u8]>),
}

impl BrickContent {
    /// The value of a uniform brick (`Empty` is 0), `None` for data.
    pub fn uniform_value(&self) -> Option<f64> {
        match self {
            BrickContent::Empty => Some(0.0),
            BrickContent::Constant(v) => Some(*v),
            BrickContent::Data(_) => None,
        }
    }

    /// Bytes of voxel data held (0 for uniform bricks).
    pub fn data_bytes(&self) -> usize {
        match self {
            BrickContent::Data(d) => d.len(),
            _ => 0,
        }
    }

    /// The padded brick as a dense buffer of `voxels` voxels of `dtype`
    /// (uniform bricks are expanded).
    pub fn to_dense(&self, voxels: usize, dtype: DType) -> Vec<u8> {
        match self {
            BrickContent::Data(d) => {
                assert_eq!(d.len(), voxels * dtype.size(), "brick size");
                d.to_vec()
            }
            _ => {
                let v = value_bytes(dtype, self.uniform_value().unwrap_or(0.0));
                v.repeat(voxels)
            }
        }
    }
}

/// The native-endian bytes of `v` converted to `dtype` (with `as`
/// semantics: exact for any value that came from that type).
pub fn value_bytes(dtype: DType, v: f64) -> Vec<u8> {
    match dtype {
        DType::U8 => (v as u8).to_ne_bytes().to_vec(),
        DType::I8 => (v as i8).to_ne_bytes().to_vec(),
        DType::U16 => (v as u16).to_ne_bytes().to_vec(),
        DType::I16 => (v as i16).to_ne_bytes().to_vec(),
        DType::U32 => (v as u32).to_ne_bytes().to_vec(),
        DType::I32 => (v as i32).to_ne_bytes().to_vec(),
        DType::F32 => (v as f32).to_ne_bytes().to_vec(),
        DType::F64 => v.to_ne_bytes().to_vec(),
    }
}

/// A brick as the loader delivers it.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadedBrick {
    pub key: BrickKey,
    pub content: BrickContent,
    /// Smallest and largest value of the brick proper (apron excluded; NaN
    /// ignored; NaN when every voxel is NaN).
    pub min: f64,
    pub max: f64,
    /// Bytes of voxel data read from the store for this brick (0 when the
    /// statistics answered).
    pub bytes_read: u64,
}

impl LoadedBrick {
    /// Whether the brick needs no pool slot (empty or constant).
    pub fn is_uniform(&self) -> bool {
        !matches!(self.content, BrickContent::Data(_))
    }
}

/// The engine's brick grid over every level of a volume.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BrickGeometry {
    /// Brick size `[z, y, x]` without apron.
    pub brick: Dims3,
    /// Apron width in voxels on every side.
    pub apron: u64,
    /// Level sizes `[z, y, x]` in voxels, level 0 first.
    pub levels: Vec<Dims3>,
    pub channels: usize,
    pub dtype: DType,
}

impl BrickGeometry {
    /// Brick size with apron: `b + 2a` per axis.
    pub fn padded(&self) -> Dims3 {
        self.brick.map(|b| b + 2 * self.apron)
    }

    /// Voxels of a padded brick.
    pub fn voxels_per_brick(&self) -> u64 {
        self.padded().iter().product()
    }

    /// Bytes of a padded brick's data.
    pub fn bytes_per_brick(&self) -> u64 {
        self.voxels_per_brick() * self.dtype.size() as u64
    }

    /// Bricks of every level and channel.
    pub fn total_bricks(&self) -> usize {
        (0..self.levels.len()).map(|l| self.bricks_at(l)).sum()
    }

    /// Number of bricks `[z, y, x]` covering level `l`.
    pub fn bricks_per_level(&self, l: usize) -> Dims3 {
        let d = self.levels[l];
        [0, 1, 2].map(|a| d[a].div_ceil(self.brick[a]))
    }

    /// Whether `key` names a brick of this volume.
    pub fn contains(&self, key: &BrickKey) -> bool {
        let l = key.level as usize;
        l < self.levels.len() && (key.channel as usize) < self.channels && {
            let n = self.bricks_per_level(l);
            (0..3).all(|a| (key.brick[a] as u64) < n[a])
        }
    }

    /// First voxel `[z, y, x]` of the brick proper (apron excluded) in its
    /// level.
    pub fn origin_of(&self, key: &BrickKey) -> Dims3 {
        [0, 1, 2].map(|a| key.brick[a] as u64 * self.brick[a])
    }

    /// First voxel of the padded brick (may be negative at the border).
    pub fn padded_origin_of(&self, key: &BrickKey) -> [i64; 3] {
        self.origin_of(key).map(|o| o as i64 - self.apron as i64)
    }

    /// Voxels `[z, y, x]` of the brick proper that lie inside the level
    /// (smaller than the brick at the far edges).
    pub fn extent_of(&self, key: &BrickKey) -> Dims3 {
        let o = self.origin_of(key);
        let d = self.levels[key.level as usize];
        [0, 1, 2].map(|a| self.brick[a].min(d[a].saturating_sub(o[a])))
    }

    /// Every brick key of one level and channel, in `[z, y, x]` order.
    pub fn keys(&self, level: usize, channel: usize) -> impl Iterator<Item = BrickKey> {
        let n = self.bricks_per_level(level);
        let (level, channel) = (level as u8, channel as u16);
        (0..n[0]).flat_map(move |z| {
            (0..n[1]).flat_map(move |y| {
                (0..n[2])
                    .map(move |x| BrickKey::new(level, channel, [z as u32, y as u32, x as u32]))
            })
        })
    }

    /// Whether every key of this volume fits [`BrickKey::pack`].
    pub fn keys_fit(&self) -> bool {
        self.levels.len() <= MAX_LEVELS
            && self.channels <= MAX_CHANNELS
            && (0..self.levels.len()).all(|l| {
                self.bricks_per_level(l)
                    .iter()
                    .all(|&n| n <= MAX_BRICKS_PER_AXIS)
            })
    }

    /// Bricks of level `l`, all channels.
    pub fn bricks_at(&self, l: usize) -> usize {
        self.bricks_per_level(l).iter().product::<u64>() as usize * self.channels
    }

    /// The levels to keep resident for good in a pool of `slots` slots of
    /// `slot_bytes`, coarsest first: the coarsest level always, and finer
    /// ones (never level 0) while all of them stay within an eighth of the
    /// pool and `max_bricks`. A pool that holds neither twice the coarsest
    /// level nor the whole volume is too small.
    pub fn pinned_levels(
        &self,
        slots: usize,
        slot_bytes: u64,
        max_bricks: usize,
    ) -> Result<Vec<usize>, PoolTooSmall> {
        let nl = self.levels.len();
        let coarsest = self.bricks_at(nl - 1);
        let all = self.total_bricks();
        if slots < 2 * coarsest && slots < all {
            return Err(PoolTooSmall {
                slots,
                needed: coarsest,
                minimum_bytes: 2 * coarsest as u64 * slot_bytes.max(1),
            });
        }
        let limit = (slots / 8).min(max_bricks).max(coarsest);
        let mut levels = vec![nl - 1];
        let mut total = coarsest;
        // Never level 0: pinning it would only keep the view's own data,
        // which the LRU does anyway while it fits.
        for l in (1..nl - 1).rev() {
            let n = self.bricks_at(l);
            if total + n > limit {
                break;
            }
            total += n;
            levels.push(l);
        }
        Ok(levels)
    }
}

/// The pool cannot hold the coarsest level (plus room to work).
#[derive(Debug, Clone)]
pub struct PoolTooSmall {
    /// Bricks the pool holds.
    pub slots: usize,
    /// Bricks the coarsest level needs (all channels).
    pub needed: usize,
    /// Pool bytes that would be enough.
    pub minimum_bytes: u64,
}

impl std::fmt::Display for PoolTooSmall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the pool holds {} bricks, but the coarsest level alone needs {} (kept resident so that every part of the volume can be drawn) plus as many to work with; give the pool at least {:.1} MiB",
            self.slots,
            self.needed,
            // (Rounded up: the figure given back must hold them.)
            (self.minimum_bytes as f64 / (1u64 << 20) as f64 * 10.0).ceil() / 10.0
        )
    }
}

impl std::error::Error for PoolTooSmall {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pinned_levels_fit_the_pool_or_the_whole_volume() {
        let geometry = |levels: Vec<Dims3>, channels| BrickGeometry {
            brick: [8; 3],
            apron: 1,
            levels,
            channels,
            dtype: DType::U8,
        };
        // One level of 2·2·2 bricks: a pool of its 8 bricks holds the whole
        // volume, though not twice the coarsest level.
        let one = geometry(vec![[16; 3]], 1);
        assert_eq!(one.pinned_levels(8, 1000, 512).unwrap(), vec![0]);
        let e = one.pinned_levels(7, 1000, 512).unwrap_err();
        assert_eq!((e.slots, e.needed, e.minimum_bytes), (7, 8, 16_000));
        // 64³, 32³, 16³, 8³ in 8³ bricks: 512, 64, 8, 1 bricks per channel.
        let four = geometry(vec![[64; 3], [32; 3], [16; 3], [8; 3]], 2);
        assert_eq!(four.pinned_levels(3, 1, 512).unwrap_err().needed, 2);
        assert_eq!(four.pinned_levels(4, 1, 512).unwrap(), vec![3]);
        // An eighth of the pool: 18 bricks for levels 3 and 2.
        assert_eq!(four.pinned_levels(143, 1, 512).unwrap(), vec![3]);
        assert_eq!(four.pinned_levels(144, 1, 512).unwrap(), vec![3, 2]);
        // Never level 0, and never past `max_bricks`.
        assert_eq!(four.pinned_levels(1 << 20, 1, 512).unwrap(), vec![3, 2, 1]);
        assert_eq!(four.pinned_levels(1 << 20, 1, 100).unwrap(), vec![3, 2]);
    }

    #[test]
    fn pack_round_trips_and_keeps_order() {
        let keys = [
            BrickKey::new(0, 0, [0, 0, 0]),
            BrickKey::new(0, 0, [0, 0, 1]),
            BrickKey::new(0, 0, [0, 1, 0]),
            BrickKey::new(0, 0, [1, 0, 0]),
            BrickKey::new(0, 1, [0, 0, 0]),
            BrickKey::new(1, 0, [0, 0, 0]),
            BrickKey::new(3, 17, [123, 4567, 65535]),
            BrickKey::new(31, 2047, [65535, 65535, 65535]),
        ];
        for w in keys.windows(2) {
            assert!(w[0] < w[1]);
            assert!(w[0].pack() < w[1].pack());
        }
        for k in keys {
            assert_eq!(BrickKey::unpack(k.pack()), k);
        }
        assert_eq!(BrickKey::new(31, 2047, [65535; 3]).pack(), u64::MAX);
        assert_eq!(
            BrickKey::new(1, 2, [3, 4, 5]).pack(),
            (1 << 59) | (2 << 48) | (3 << 32) | (4 << 16) | 5
        );
        assert!(!BrickKey::new(32, 0, [0; 3]).fits());
        assert!(!BrickKey::new(0, 2048, [0; 3]).fits());
        assert!(!BrickKey::new(0, 0, [0, 65536, 0]).fits());
    }

    #[test]
    #[should_panic]
    fn pack_refuses_overflow() {
        BrickKey::new(0, 0, [70000, 0, 0]).pack();
    }

    #[test]
    fn geometry_helpers() {
        let g = BrickGeometry {
            brick: [8, 12, 20],
            apron: 2,
            levels: vec![[37, 45, 51], [19, 23, 26]],
            channels: 2,
            dtype: DType::U16,
        };
        assert_eq!(g.padded(), [12, 16, 24]);
        assert_eq!(g.bytes_per_brick(), 12 * 16 * 24 * 2);
        assert_eq!(g.bricks_per_level(0), [5, 4, 3]);
        assert_eq!(g.bricks_per_level(1), [3, 2, 2]);
        let k = BrickKey::new(0, 1, [4, 3, 2]);
        assert!(g.contains(&k));
        assert!(!g.contains(&BrickKey::new(0, 2, [0; 3])));
        assert!(!g.contains(&BrickKey::new(2, 0, [0; 3])));
        assert!(!g.contains(&BrickKey::new(1, 0, [3, 0, 0])));
        assert_eq!(g.origin_of(&k), [32, 36, 40]);
        assert_eq!(g.padded_origin_of(&BrickKey::new(0, 0, [0; 3])), [-2; 3]);
        assert_eq!(g.extent_of(&k), [5, 9, 11]);
        assert_eq!(g.keys(1, 0).count(), 12);
        assert_eq!(g.keys(1, 1).last(), Some(BrickKey::new(1, 1, [2, 1, 1])));
        assert!(g.keys_fit());
    }

    #[test]
    fn dense_expansion() {
        assert_eq!(BrickContent::Empty.to_dense(3, DType::U16), vec![0u8; 6]);
        assert_eq!(
            BrickContent::Constant(-2.0).to_dense(2, DType::I16),
            [(-2i16).to_ne_bytes(), (-2i16).to_ne_bytes()].concat()
        );
        assert_eq!(
            BrickContent::Constant(1.5).to_dense(1, DType::F32),
            1.5f32.to_ne_bytes().to_vec()
        );
    }
}
