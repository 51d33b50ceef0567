//! A sparse voxel grid of 8x8x8 bricks in a hash map (docs/ALGORITHMS.md section 4).
//!
//! Voxel `i` spans `[i r, (i+1) r)` per axis; its brick is `i >> 3` (floor division, so
//! negative coordinates work) and its slot in the brick is `i & 7`. A brick holds a 512-bit
//! mask of which voxels are allocated (unallocated means unknown) and the values of its
//! z-layers that hold any: 64 values per layer, allocated as a layer's first voxel is (see
//! [`Brick`]). The values live on the heap, so rehashing moves a hundred bytes a brick, not
//! kilobytes.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Voxels per brick edge.
pub const BRICK_EDGE: i32 = 8;
/// Voxels per brick.
pub const BRICK_VOXELS: usize = 512;
const BRICK_SHIFT: u32 = 3;

/// Integer voxel coordinates.
///
/// ```
/// use mrfmap::map::VoxelKey;
/// let k = VoxelKey::from_point([-0.01, 0.0, 0.049], 0.05);
/// assert_eq!(k, VoxelKey([-1, 0, 0]));
/// assert_eq!(k.brick(), mrfmap::map::BrickKey([-1, 0, 0]));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VoxelKey(pub [i32; 3]);

/// Integer brick coordinates (voxel coordinates `>> 3`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BrickKey(pub [i32; 3]);

impl VoxelKey {
    /// The voxel containing world point `p` at resolution `r`.
    #[inline]
    pub fn from_point(p: [f64; 3], r: f64) -> Self {
        VoxelKey(p.map(|x| floor_i32(x / r)))
    }

    /// World coordinates of the voxel centre.
    #[inline]
    pub fn center(&self, r: f64) -> [f64; 3] {
        self.0.map(|i| (i as f64 + 0.5) * r)
    }

    /// The brick holding this voxel.
    #[inline]
    pub fn brick(&self) -> BrickKey {
        BrickKey(self.0.map(|i| i >> BRICK_SHIFT))
    }

    /// Linear slot of this voxel inside its brick (`x + 8 y + 64 z`).
    #[inline]
    pub fn slot(&self) -> usize {
        let [x, y, z] = self.0.map(|i| (i & (BRICK_EDGE - 1)) as usize);
        x | (y << 3) | (z << 6)
    }
}

impl BrickKey {
    /// The voxel at `slot` of this brick.
    #[inline]
    pub fn voxel(&self, slot: usize) -> VoxelKey {
        let local = [slot & 7, (slot >> 3) & 7, slot >> 6];
        VoxelKey([0, 1, 2].map(|a| (self.0[a] << BRICK_SHIFT) + local[a] as i32))
    }
}

/// `x.floor() as i32`, identical for every input (saturating alike, NaN to 0), without the
/// call into libm that `floor` costs on baseline x86-64 (it was 11% of the per-pixel setup of
/// log-odds projection).
///
/// ```
/// use mrfmap::map::floor_i32;
/// assert_eq!((floor_i32(-0.5), floor_i32(2.0), floor_i32(-3e10)), (-1, 2, i32::MIN));
/// ```
#[inline]
pub fn floor_i32(x: f64) -> i32 {
    let t = x as i32; // toward zero, saturating
    t.saturating_sub(((t as f64) > x) as i32) // branch-free: the sign of x is unpredictable
}

/// [`floor_i32`] in a form the compiler runs in SIMD lanes: the same value for every input
/// but NaN (which gives an unspecified number). The clamp, the rounding and the conversion are
/// additions and comparisons of `f64` (`1.5 * 2^52` added to an integer below `2^51` in size
/// leaves it in the low 32 bits), where `as i32` is a scalar conversion with its saturation
/// checks (in a lane loop over a row of pixels, that conversion was a third of the loop).
///
/// `FLOOR_INSTRUCTION` says whether the caller is compiled where `floor` is one instruction
/// (SSE4.1's `roundpd`, in the AVX2 copies of the lane loops): the rounding is then that
/// instruction, where on baseline x86-64 `floor` is a call into libm and the rounding is made
/// of additions and a comparison instead. (The instruction alone made icl-livingroom-5's
/// frames at 0.05 m take 0.935x the time: BENCHMARKS.md, session 43.)
#[inline(always)]
pub(crate) fn floor_i32_lanes<const FLOOR_INSTRUCTION: bool>(x: f64) -> i32 {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52
    let c = if x < i32::MAX as f64 { x } else { i32::MAX as f64 };
    let c = if c > i32::MIN as f64 { c } else { i32::MIN as f64 };
    let floor = if FLOOR_INSTRUCTION {
        c.floor()
    } else {
        let nearest = (c + MAGIC) - MAGIC;
        if nearest > c { nearest - 1.0 } else { nearest }
    };
    (floor + MAGIC).to_bits() as u32 as i32
}

/// A 512-bit set over a brick's slots.
pub type SlotMask = [u64; 8];

/// Is `slot` set in `mask`?
#[inline]
pub fn mask_has(mask: &SlotMask, slot: usize) -> bool {
    mask[slot >> 6] >> (slot & 63) & 1 == 1
}

/// Sets `slot` in `mask`.
#[inline]
pub fn mask_set(mask: &mut SlotMask, slot: usize) {
    mask[slot >> 6] |= 1 << (slot & 63);
}

/// The slots of brick `brick` whose voxels lie in the box of keys `lo..=hi` (inclusive per
/// axis, as [`crate::map::box_keys`] gives them).
pub fn box_slots(brick: BrickKey, lo: [i32; 3], hi: [i32; 3]) -> SlotMask {
    // Per axis the brick's local coordinates in the box, half-open and within 0..8.
    let range = |a: usize| {
        let base = brick.0[a] * BRICK_EDGE;
        ((lo[a] - base).clamp(0, BRICK_EDGE), (hi[a] + 1 - base).clamp(0, BRICK_EDGE))
    };
    let ([x0, x1], [y0, y1], [z0, z1]) = (range(0).into(), range(1).into(), range(2).into());
    let row = if x0 < x1 { (u64::MAX >> (64 - (x1 - x0))) << x0 } else { 0 };
    let layer = (y0..y1).fold(0u64, |m, y| m | row << (8 * y));
    std::array::from_fn(|z| if (z0..z1).contains(&(z as i32)) { layer } else { 0 })
}

/// Iterates the set slots of `mask` in increasing order.
pub fn mask_slots(mask: &SlotMask) -> impl Iterator<Item = usize> + '_ {
    MaskSlots { mask, word: 0, bits: mask[0] }
}

/// [`mask_slots`]'s iterator: one word's bits at a time (a `flat_map` over the words cost a
/// log-odds frame 3% more instructions where bricks are updated slot by slot).
struct MaskSlots<'a> {
    mask: &'a SlotMask,
    /// The word being read, and its bits not yet returned.
    word: usize,
    bits: u64,
}

impl Iterator for MaskSlots<'_> {
    type Item = usize;

    #[inline]
    fn next(&mut self) -> Option<usize> {
        while self.bits == 0 {
            self.word += 1;
            self.bits = *self.mask.get(self.word)?;
        }
        let b = self.bits.trailing_zeros() as usize;
        self.bits &= self.bits - 1;
        Some(self.word * 64 + b)
    }
}

/// Checks a voxel edge: a positive, finite number of metres.
pub fn check_resolution(resolution: f64) -> crate::Result<()> {
    if !(resolution > 0.0 && resolution.is_finite()) {
        return Err(crate::Error::Invalid(format!("resolution must be a positive number of metres, got {resolution}")));
    }
    Ok(())
}

/// Bricks in first-seen order, each with a value: a hash index over a vector, so per-task
/// scratch data (a scan's marks, a frame's counts) stays contiguous and comes out in a fixed
/// order, whatever the hash.
///
/// ```
/// use mrfmap::map::{BrickKey, BrickList};
/// let mut list = BrickList::default();
/// let a = list.index_or_insert_with(BrickKey([0, 0, 0]), || 0u32);
/// *list.value_mut(a) += 5;
/// assert_eq!(list.index_or_insert_with(BrickKey([0, 0, 0]), || 0), a);
/// assert_eq!(list.into_items(), vec![(BrickKey([0, 0, 0]), 5)]);
/// ```
#[derive(Clone, Debug)]
pub struct BrickList<T> {
    index: FxHashMap<BrickKey, u32>,
    items: Vec<(BrickKey, T)>,
}

impl<T> Default for BrickList<T> {
    fn default() -> Self {
        BrickList { index: FxHashMap::default(), items: Vec::new() }
    }
}

impl<T> BrickList<T> {
    /// Index of `key`'s entry, adding `new()` for a brick not seen before.
    #[inline]
    pub fn index_or_insert_with(&mut self, key: BrickKey, new: impl FnOnce() -> T) -> usize {
        let next = self.items.len() as u32;
        let i = *self.index.entry(key).or_insert(next);
        if i == next {
            self.items.push((key, new()));
        }
        i as usize
    }

    /// The value at index `i`.
    #[inline]
    pub fn value_mut(&mut self, i: usize) -> &mut T {
        &mut self.items[i].1
    }

    /// Entries in first-seen order.
    pub fn iter(&self) -> impl Iterator<Item = &(BrickKey, T)> + '_ {
        self.items.iter()
    }

    /// The entries, in first-seen order.
    pub fn into_items(self) -> Vec<(BrickKey, T)> {
        self.items
    }
}

/// 8x8x8 voxels with an allocation mask, stored by layer: the 64 voxels of one z-layer (one
/// word of the mask) are allocated together, the first time one of them is. A map from planar
/// scans fills one layer of its bricks, a surface seen from above a few: they pay for what
/// they hold, not for whole bricks (a laser log's map took 8x the memory it needed).
#[derive(Clone, Debug)]
pub struct Brick<V> {
    mask: SlotMask,
    /// Per layer, its place in `values` (in 64-value units), [`NO_LAYER`] if not allocated.
    layer: [u8; 8],
    /// 64 values per allocated layer, in the order the layers were allocated.
    values: Vec<V>,
}

/// [`Brick::layer`] of a layer with no values.
const NO_LAYER: u8 = u8::MAX;

/// Voxels per layer of a brick (one mask word).
const LAYER: usize = 64;

/// [`Brick::layer`] of a brick whose layers are all allocated, in slot order.
const NATURAL: [u8; 8] = [0, 1, 2, 3, 4, 5, 6, 7];

impl<V: Copy + Default> Default for Brick<V> {
    fn default() -> Self {
        Brick { mask: [0; 8], layer: [NO_LAYER; 8], values: Vec::new() }
    }
}

impl<V: Copy + Default> Brick<V> {
    /// Which slots are allocated.
    pub fn mask(&self) -> &SlotMask {
        &self.mask
    }

    /// Where `slot`'s value is in `values` (its layer must be allocated).
    #[inline]
    fn at(&self, slot: usize) -> usize {
        self.layer[slot / LAYER] as usize * LAYER + slot % LAYER
    }

    /// Allocates the layers of `slots` that have no values yet, all at once.
    #[inline]
    fn allocate_layers(&mut self, slots: &SlotMask) {
        let missing: [bool; 8] = std::array::from_fn(|w| slots[w] != 0 && self.layer[w] == NO_LAYER);
        let count = missing.iter().filter(|&&m| m).count();
        if count == 0 {
            return;
        }
        self.values.reserve(count * LAYER);
        for w in (0..8).filter(|&w| missing[w]) {
            self.layer[w] = (self.values.len() / LAYER) as u8;
            self.values.resize(self.values.len() + LAYER, V::default());
        }
        // A brick with every layer keeps them in slot order, so that it reads as one array
        // ([`Brick::dense`]).
        if self.values.len() == BRICK_VOXELS && self.layer != NATURAL {
            let mut ordered = Vec::with_capacity(BRICK_VOXELS);
            for w in 0..8 {
                let at = self.layer[w] as usize * LAYER;
                ordered.extend_from_slice(&self.values[at..at + LAYER]);
            }
            (self.values, self.layer) = (ordered, NATURAL);
        }
    }

    /// The 512 values in slot order when every voxel is allocated (a dense brick, read without
    /// the mask and the layer table: the MRF's bricks are all dense).
    #[inline]
    pub fn dense(&self) -> Option<&[V; BRICK_VOXELS]> {
        if self.mask != [u64::MAX; 8] {
            return None;
        }
        self.values.as_slice().try_into().ok()
    }

    /// [`Brick::dense`], mutable.
    #[inline]
    pub fn dense_mut(&mut self) -> Option<&mut [V; BRICK_VOXELS]> {
        if self.mask != [u64::MAX; 8] {
            return None;
        }
        self.values.as_mut_slice().try_into().ok()
    }

    /// Value at `slot` if allocated.
    #[inline]
    pub fn get(&self, slot: usize) -> Option<&V> {
        mask_has(&self.mask, slot).then(|| &self.values[self.at(slot)])
    }

    /// Mutable value at `slot`, allocating it with `init` first if needed.
    #[inline]
    pub fn get_or_insert(&mut self, slot: usize, init: V) -> &mut V {
        if !mask_has(&self.mask, slot) {
            if self.layer[slot / LAYER] == NO_LAYER {
                let mut one = [0; 8];
                mask_set(&mut one, slot);
                self.allocate_layers(&one);
            }
            mask_set(&mut self.mask, slot);
            let at = self.at(slot);
            self.values[at] = init;
        }
        let at = self.at(slot);
        &mut self.values[at]
    }

    /// Calls `update` on the value of every slot in `slots`, allocating those not allocated
    /// yet with `init` first: [`Brick::get_or_insert`] for a set of slots, one mask word at a
    /// time (per slot, the mask's test and set were a twentieth of a projected log-odds frame).
    #[inline]
    pub fn update_slots(&mut self, slots: &SlotMask, init: V, mut update: impl FnMut(&mut V)) {
        self.allocate_layers(slots);
        for (w, &want) in slots.iter().enumerate().filter(|(_, want)| **want != 0) {
            let base = self.layer[w] as usize * LAYER;
            let layer = &mut self.values[base..base + LAYER];
            let (mut new, mut all) = (want & !self.mask[w], want);
            // Whole layers (most of a projected frame's free space) in plain loops, which the
            // compiler runs in lanes, instead of a bit scan per voxel.
            if new == u64::MAX {
                layer.fill(init);
                new = 0;
            }
            while new != 0 {
                layer[new.trailing_zeros() as usize] = init;
                new &= new - 1;
            }
            self.mask[w] |= want;
            if all == u64::MAX {
                // (A `for` loop: `for_each(&mut update)` called the update through the
                // reference, per voxel, not inlined.)
                for v in layer.iter_mut() {
                    update(v);
                }
                all = 0;
            }
            while all != 0 {
                update(&mut layer[all.trailing_zeros() as usize]);
                all &= all - 1;
            }
        }
    }

    /// Number of allocated voxels.
    pub fn len(&self) -> usize {
        self.mask.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// True if no voxel is allocated.
    pub fn is_empty(&self) -> bool {
        self.mask.iter().all(|w| *w == 0)
    }

    /// Frees `slot` (unknown again); true if it was allocated. (Its layer keeps its values.)
    pub fn remove(&mut self, slot: usize) -> bool {
        let had = mask_has(&self.mask, slot);
        self.mask[slot >> 6] &= !(1 << (slot & 63));
        had
    }

    /// Mutable value at `slot` if allocated.
    #[inline]
    pub fn get_mut(&mut self, slot: usize) -> Option<&mut V> {
        let at = self.at(slot);
        mask_has(&self.mask, slot).then(|| &mut self.values[at])
    }

    /// Allocated `(slot, value)` pairs in slot order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, &V)> + '_ {
        mask_slots(&self.mask).map(move |s| (s, &self.values[self.at(s)]))
    }

    /// Calls `f` on every allocated value in slot order (as [`Brick::iter`]), a layer at a
    /// time: a whole layer in a plain loop, not a bit scan per voxel (free space fills whole
    /// layers; saving a map this way made a whole 0.02 m build 0.94x the time). (A `for`
    /// loop, not `for_each(&mut f)`, whose call through the reference was not inlined.)
    pub fn for_each_value(&self, mut f: impl FnMut(&V)) {
        for (w, &bits) in self.mask.iter().enumerate().filter(|(_, bits)| **bits != 0) {
            let base = self.layer[w] as usize * LAYER;
            let layer = &self.values[base..base + LAYER];
            if bits == u64::MAX {
                for v in layer {
                    f(v);
                }
                continue;
            }
            let mut left = bits;
            while left != 0 {
                f(&layer[left.trailing_zeros() as usize]);
                left &= left - 1;
            }
        }
    }

    /// The allocated slots whose value satisfies `f` (a layer at a time).
    #[inline]
    pub fn slots_where(&self, f: impl Fn(&V) -> bool) -> SlotMask {
        std::array::from_fn(|w| {
            let bits = self.mask[w];
            if bits == 0 {
                return 0;
            }
            let base = self.layer[w] as usize * LAYER;
            let layer = &self.values[base..base + LAYER];
            layer.iter().enumerate().fold(0u64, |m, (i, v)| m | (f(v) as u64) << i) & bits
        })
    }

    /// The same slots with every allocated value mapped through `f` (layer by layer).
    pub fn map<W: Copy + Default>(&self, mut f: impl FnMut(&V) -> W) -> Brick<W> {
        let mut values = vec![W::default(); self.values.len()];
        for (w, &bits) in self.mask.iter().enumerate().filter(|(_, bits)| **bits != 0) {
            let base = self.layer[w] as usize * LAYER;
            let mut left = bits;
            while left != 0 {
                let at = base + left.trailing_zeros() as usize;
                values[at] = f(&self.values[at]);
                left &= left - 1;
            }
        }
        Brick { mask: self.mask, layer: self.layer, values }
    }

    /// Heap bytes of the values (what the brick holds beyond its own size).
    pub fn heap_bytes(&self) -> usize {
        self.values.capacity() * std::mem::size_of::<V>()
    }
}

/// A sparse grid of voxels of type `V` at a fixed resolution.
///
/// ```
/// use mrfmap::map::{Grid, VoxelKey};
/// let mut grid: Grid<f32> = Grid::new(0.05).unwrap();
/// *grid.get_or_insert(VoxelKey([-3, 7, 100]), 0.0) += 0.85;
/// assert_eq!(grid.get(VoxelKey([-3, 7, 100])), Some(&0.85));
/// assert_eq!(grid.get(VoxelKey([-3, 7, 101])), None);
/// assert_eq!((grid.len(), grid.brick_count()), (1, 1));
/// ```
#[derive(Clone, Debug)]
pub struct Grid<V> {
    resolution: f64,
    bricks: FxHashMap<BrickKey, Brick<V>>,
}

impl<V: Copy + Default> Grid<V> {
    /// An empty grid; the resolution (voxel edge in metres) must be positive and finite.
    pub fn new(resolution: f64) -> crate::Result<Self> {
        check_resolution(resolution)?;
        Ok(Grid { resolution, bricks: FxHashMap::default() })
    }

    /// Voxel edge length in metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Value of an allocated voxel.
    #[inline]
    pub fn get(&self, key: VoxelKey) -> Option<&V> {
        self.bricks.get(&key.brick())?.get(key.slot())
    }

    /// Mutable value of a voxel, allocating it (with `init`) and its brick if needed.
    #[inline]
    pub fn get_or_insert(&mut self, key: VoxelKey, init: V) -> &mut V {
        self.brick_or_insert(key.brick()).get_or_insert(key.slot(), init)
    }

    /// Mutable value of an allocated voxel.
    #[inline]
    pub fn get_mut(&mut self, key: VoxelKey) -> Option<&mut V> {
        self.bricks.get_mut(&key.brick())?.get_mut(key.slot())
    }

    /// Frees a voxel (unknown again), dropping its brick when it was the last; true if it
    /// was allocated.
    pub fn remove(&mut self, key: VoxelKey) -> bool {
        let bk = key.brick();
        let Some(brick) = self.bricks.get_mut(&bk) else { return false };
        let had = brick.remove(key.slot());
        if brick.is_empty() {
            self.bricks.remove(&bk);
        }
        had
    }

    /// Moves every voxel of `other` into this grid (same resolution): its bricks as they are
    /// where this grid has none, voxel by voxel (`other`'s value winning) where both do.
    pub fn absorb(&mut self, other: Grid<V>) {
        for (key, brick) in other.bricks {
            match self.bricks.entry(key) {
                std::collections::hash_map::Entry::Vacant(slot) => {
                    slot.insert(brick);
                }
                std::collections::hash_map::Entry::Occupied(mut mine) => {
                    for (slot, v) in brick.iter() {
                        *mine.get_mut().get_or_insert(slot, *v) = *v;
                    }
                }
            }
        }
    }

    /// Keeps the bricks for which `keep` is true.
    pub fn retain_bricks(&mut self, mut keep: impl FnMut(BrickKey) -> bool) {
        self.bricks.retain(|k, _| keep(*k));
    }

    /// Drops whole bricks (absent ones are ignored).
    pub fn remove_bricks(&mut self, keys: &[BrickKey]) {
        for k in keys {
            self.bricks.remove(k);
        }
    }

    /// Sets a voxel's value, allocating it.
    pub fn insert(&mut self, key: VoxelKey, value: V) {
        *self.get_or_insert(key, value) = value;
    }

    /// A brick, allocating an empty one if needed.
    pub fn brick_or_insert(&mut self, key: BrickKey) -> &mut Brick<V> {
        self.bricks.entry(key).or_default()
    }

    /// A brick if present.
    pub fn brick(&self, key: BrickKey) -> Option<&Brick<V>> {
        self.bricks.get(&key)
    }

    /// The brick `key`, mutable, if present.
    pub fn brick_mut(&mut self, key: BrickKey) -> Option<&mut Brick<V>> {
        self.bricks.get_mut(&key)
    }

    /// Bricks in unspecified order.
    pub fn bricks(&self) -> impl Iterator<Item = (&BrickKey, &Brick<V>)> + '_ {
        self.bricks.iter()
    }

    /// Calls `update` on the brick of every key of `work` with that key's value, allocating
    /// missing bricks, in parallel, and returns what it returned per brick (in no particular
    /// order). The work grows with `work`, not with the grid: the bricks are taken out of the
    /// hash map, updated, and put back.
    ///
    /// ```
    /// use mrfmap::map::{BrickKey, Grid};
    /// let mut grid: Grid<f32> = Grid::new(0.1).unwrap();
    /// let work: rustc_hash::FxHashMap<BrickKey, usize> = [(BrickKey([0, 0, 0]), 3), (BrickKey([-1, 2, 0]), 5)].into_iter().collect();
    /// let mut lens = grid.update_bricks(&work, |brick, slot| {
    ///     *brick.get_or_insert(*slot, 0.0) += 1.0;
    ///     brick.len()
    /// });
    /// assert_eq!((grid.len(), grid.brick_count()), (2, 2));
    /// lens.sort();
    /// assert_eq!(lens, vec![(BrickKey([-1, 2, 0]), 1), (BrickKey([0, 0, 0]), 1)]);
    /// ```
    pub fn update_bricks<T: Sync, R: Send>(
        &mut self,
        work: &FxHashMap<BrickKey, T>,
        update: impl Fn(&mut Brick<V>, &T) -> R + Sync,
    ) -> Vec<(BrickKey, R)>
    where
        V: Send,
    {
        let mut taken: Vec<(BrickKey, Brick<V>, &T)> =
            work.iter().map(|(k, t)| (*k, self.bricks.remove(k).unwrap_or_default(), t)).collect();
        let results = taken.par_iter_mut().map(|(k, brick, t)| (*k, update(brick, t))).collect();
        self.bricks.extend(taken.into_iter().map(|(k, brick, _)| (k, brick)));
        results
    }

    /// Brick keys in sorted order, for deterministic output.
    pub fn sorted_brick_keys(&self) -> Vec<BrickKey> {
        let mut keys: Vec<BrickKey> = self.bricks.keys().copied().collect();
        keys.sort_unstable();
        keys
    }

    /// All allocated voxels in unspecified order.
    pub fn iter(&self) -> impl Iterator<Item = (VoxelKey, &V)> + '_ {
        self.bricks.iter().flat_map(|(bk, b)| b.iter().map(move |(s, v)| (bk.voxel(s), v)))
    }

    /// Number of allocated voxels.
    pub fn len(&self) -> usize {
        self.bricks.values().map(|b| b.len()).sum()
    }

    /// True when nothing is allocated.
    pub fn is_empty(&self) -> bool {
        self.bricks.values().all(|b| b.is_empty())
    }

    /// Number of allocated bricks.
    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    /// Bytes used by bricks and the hash table (an estimate of the heap footprint).
    pub fn memory_bytes(&self) -> usize {
        let entry = std::mem::size_of::<(BrickKey, Brick<V>)>() + 1; // + hashbrown control byte
        self.bricks.capacity() * entry + self.bricks.values().map(Brick::heap_bytes).sum::<usize>()
    }

    /// Inclusive min and max voxel keys of allocated voxels, `None` when empty.
    pub fn key_bounds(&self) -> Option<(VoxelKey, VoxelKey)> {
        let mut lo = [i32::MAX; 3];
        let mut hi = [i32::MIN; 3];
        for (k, _) in self.iter() {
            for a in 0..3 {
                lo[a] = lo[a].min(k.0[a]);
                hi[a] = hi[a].max(k.0[a]);
            }
        }
        (lo[0] <= hi[0]).then_some((VoxelKey(lo), VoxelKey(hi)))
    }

    /// Inclusive min and max voxel keys of the allocated *bricks* (a superset of
    /// [`Grid::key_bounds`], 512 times cheaper to compute), `None` when empty.
    pub fn brick_key_bounds(&self) -> Option<(VoxelKey, VoxelKey)> {
        let mut lo = [i32::MAX; 3];
        let mut hi = [i32::MIN; 3];
        for k in self.bricks.keys() {
            for a in 0..3 {
                lo[a] = lo[a].min(k.0[a] << BRICK_SHIFT);
                hi[a] = hi[a].max((k.0[a] << BRICK_SHIFT) + BRICK_EDGE - 1);
            }
        }
        (lo[0] <= hi[0]).then_some((VoxelKey(lo), VoxelKey(hi)))
    }

    /// A grid of the same shape with every value mapped through `f`.
    pub fn map<W: Copy + Default>(&self, mut f: impl FnMut(&V) -> W) -> Grid<W> {
        let mut out = Grid { resolution: self.resolution, bricks: FxHashMap::default() };
        out.bricks.reserve(self.bricks.len());
        out.bricks.extend(self.bricks.iter().map(|(k, b)| (*k, b.map(&mut f))));
        out
    }

    /// [`Grid::map`], giving up this grid: each brick's values are freed once mapped, so
    /// the two grids are not both whole at once.
    pub fn into_map<W: Copy + Default>(self, mut f: impl FnMut(&V) -> W) -> Grid<W> {
        let mut out = Grid { resolution: self.resolution, bricks: FxHashMap::default() };
        out.bricks.reserve(self.bricks.len());
        out.bricks.extend(self.bricks.into_iter().map(|(k, b)| (k, b.map(&mut f))));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// A brick's slots in a box of keys are those of its voxels that the box holds, for
    /// boxes that cut it, hold it, or miss it.
    #[test]
    fn box_slots_are_the_voxels_in_the_box() {
        let mut rng = Rng::new(5);
        let (mut cut, mut whole, mut none) = (0, 0, 0);
        for _ in 0..2000 {
            let brick = BrickKey([0; 3].map(|_| rng.range(-3.0, 3.0).floor() as i32));
            let lo: [i32; 3] = std::array::from_fn(|a| brick.0[a] * BRICK_EDGE + rng.range(-12.0, 10.0).floor() as i32);
            let hi: [i32; 3] = std::array::from_fn(|a| lo[a] + rng.range(-2.0, 24.0).floor() as i32);
            let got = box_slots(brick, lo, hi);
            let want: SlotMask = std::array::from_fn(|w| {
                (0..64).fold(0u64, |m, b| {
                    let k = brick.voxel(w * 64 + b).0;
                    m | (((0..3).all(|a| k[a] >= lo[a] && k[a] <= hi[a])) as u64) << b
                })
            });
            assert_eq!(got, want, "{brick:?} {lo:?} {hi:?}");
            match got {
                m if m == [u64::MAX; 8] => whole += 1,
                m if m == [0; 8] => none += 1,
                _ => cut += 1,
            }
        }
        assert!(cut > 100 && whole > 20 && none > 100, "{cut} {whole} {none}");
    }

    #[test]
    fn keys_round_trip_through_bricks() {
        let mut rng = Rng::new(3);
        for _ in 0..10_000 {
            let k = VoxelKey([0; 3].map(|_| (rng.next_u64() % 2001) as i32 - 1000));
            assert_eq!(k.brick().voxel(k.slot()), k);
            for a in 0..3 {
                assert_eq!(k.brick().0[a], k.0[a].div_euclid(8));
            }
        }
    }

    #[test]
    fn floor_i32_equals_floor() {
        let mut rng = Rng::new(5);
        let special = [0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 1e-300, -1e-300, 2147483647.5, -2147483648.0, -2147483648.5];
        let extremes = [3e9, -3e9, f64::INFINITY, f64::NEG_INFINITY, f64::NAN, f64::MAX, f64::MIN];
        let random = (0..100_000).map(|i| rng.range(-1.0, 1.0) * 10f64.powi(i % 12));
        for x in special.into_iter().chain(extremes).chain(random) {
            assert_eq!(floor_i32(x), x.floor() as i32, "{x}");
        }
    }

    /// [`floor_i32_lanes`], either way of rounding, is [`floor_i32`] for every number: around
    /// each integer, at the halves (where rounding to nearest picks an even integer), at the
    /// ends of `i32` and beyond, and at random.
    #[test]
    fn floor_in_lanes_is_floor_i32() {
        let mut rng = crate::random::Rng::new(5);
        let mut xs = vec![0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, -2.5, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300];
        for k in [0.0, 1.0, -1.0, 2.0, 1e6, -1e6, 2f64.powi(31), -(2f64.powi(31)), 2f64.powi(31) - 1.0, 2f64.powi(52)] {
            for d in [0.0, 0.25, 0.5, 0.75, 1e-9, -1e-9, -0.5, f64::EPSILON * k.abs().max(1.0)] {
                xs.push(k + d);
                xs.push(-(k + d));
            }
        }
        for _ in 0..100_000 {
            let scale = 10f64.powf(rng.range(-3.0, 12.0));
            xs.push(rng.range(-1.0, 1.0) * scale);
        }
        for x in xs {
            assert_eq!(floor_i32_lanes::<false>(x), floor_i32(x), "{x}");
            assert_eq!(floor_i32_lanes::<true>(x), floor_i32(x), "{x}");
        }
    }

    #[test]
    fn from_point_uses_floor() {
        let r = 0.1;
        assert_eq!(VoxelKey::from_point([0.0, -1e-12, 0.35], r), VoxelKey([0, -1, 3]));
        let c = VoxelKey([-4, 2, 9]).center(r);
        assert_eq!(VoxelKey::from_point(c, r), VoxelKey([-4, 2, 9]));
    }

    #[test]
    fn grid_matches_a_plain_map() {
        let mut rng = Rng::new(11);
        let mut grid: Grid<u32> = Grid::new(0.02).unwrap();
        let mut reference = std::collections::BTreeMap::new();
        for i in 0..5000u32 {
            let k = VoxelKey([0; 3].map(|_| (rng.next_u64() % 64) as i32 - 32));
            grid.insert(k, i);
            reference.insert(k, i);
        }
        assert_eq!(grid.len(), reference.len());
        let mut got: Vec<(VoxelKey, u32)> = grid.iter().map(|(k, v)| (k, *v)).collect();
        got.sort();
        assert_eq!(got, reference.into_iter().collect::<Vec<_>>());
        let (lo, hi) = grid.key_bounds().unwrap();
        assert!(lo.0.iter().all(|&v| v >= -32) && hi.0.iter().all(|&v| v < 32));
        let (blo, bhi) = grid.brick_key_bounds().unwrap();
        assert!(
            (0..3).all(|a| blo.0[a] <= lo.0[a]
                && lo.0[a] - blo.0[a] < 8
                && bhi.0[a] >= hi.0[a]
                && bhi.0[a] - hi.0[a] < 8)
        );
        assert!(Grid::<f32>::new(0.0).is_err());
        assert!(Grid::<f32>::new(f64::NAN).is_err());
    }

    #[test]
    fn mask_iteration_in_order() {
        let mut m = [0u64; 8];
        for s in [0, 5, 63, 64, 300, 511] {
            mask_set(&mut m, s);
        }
        assert_eq!(mask_slots(&m).collect::<Vec<_>>(), vec![0, 5, 63, 64, 300, 511]);
    }

    #[test]
    fn update_slots_is_get_or_insert_per_slot() {
        let mut rng = Rng::new(17);
        let (mut fast, mut slow) = (Brick::<u32>::default(), Brick::<u32>::default());
        for round in 0..50u32 {
            // Sparse and dense masks and whole words, overlapping what earlier rounds allocated.
            let slots: SlotMask = std::array::from_fn(|_| match rng.next_u64() % 4 {
                0 => u64::MAX,
                _ => rng.next_u64() & rng.next_u64() & rng.next_u64(),
            });
            fast.update_slots(&slots, 1000 + round, |v| *v = v.wrapping_mul(3) + round);
            for slot in mask_slots(&slots) {
                let v = slow.get_or_insert(slot, 1000 + round);
                *v = v.wrapping_mul(3) + round;
            }
            assert_eq!(fast.mask(), slow.mask());
            assert!(fast.iter().eq(slow.iter()), "round {round}");
        }
        assert!(fast.len() > 400, "the masks should have filled most of the brick");
    }

    #[test]
    fn bricks_hold_the_layers_they_use() {
        // A planar map: one z-layer per brick, 64 values each, not 512.
        let mut grid: Grid<f32> = Grid::new(0.05).unwrap();
        for x in -20..20 {
            for y in -20..20 {
                grid.insert(VoxelKey([x, y, 3]), (x * y) as f32);
            }
        }
        let values: usize = grid.bricks().map(|(_, b)| b.heap_bytes()).sum();
        assert_eq!(values, grid.brick_count() * 64 * 4);
        assert!((-20..20).all(|x| grid.get(VoxelKey([x, x, 3])) == Some(&((x * x) as f32))));
        assert_eq!(grid.get(VoxelKey([0, 0, 2])), None);
        // Layers allocated out of order, by single voxels and by masks, removed and refilled.
        let mut brick = Brick::<u32>::default();
        *brick.get_or_insert(7 * 64 + 5, 1) += 1;
        brick.update_slots(&[0, 0, 1 << 9, 0, 0, 0, 0, 1 << 5], 10, |v| *v += 100);
        assert_eq!(brick.iter().map(|(s, v)| (s, *v)).collect::<Vec<_>>(), [(2 * 64 + 9, 110), (7 * 64 + 5, 102)]);
        assert_eq!(brick.heap_bytes(), 2 * 64 * 4);
        assert!(brick.remove(2 * 64 + 9) && !brick.remove(2 * 64 + 9));
        assert_eq!((brick.get(2 * 64 + 9), brick.len()), (None, 1));
        assert_eq!(*brick.get_or_insert(2 * 64 + 9, 5), 5, "a freed voxel comes back with its init");
        assert_eq!(brick.get_mut(3), None);
        assert!(brick.dense().is_none());
        // Filled, whatever the order its layers came in, it reads as one array in slot order.
        for slot in (0..BRICK_VOXELS).rev() {
            brick.get_or_insert(slot, slot as u32);
        }
        let dense = brick.dense().unwrap();
        assert!(dense.iter().enumerate().all(|(slot, &v)| brick.get(slot) == Some(&v)));
        assert_eq!((dense[7 * 64 + 5], dense[2 * 64 + 9], dense[100]), (102, 5, 100));
        brick.dense_mut().unwrap()[100] = 7;
        assert_eq!(brick.get(100), Some(&7));
        // Mapped, given up or not, the same voxels with the mapped values.
        let doubled = grid.map(|v| 2.0 * v);
        let given_up = grid.clone().into_map(|v| 2.0 * v);
        assert_eq!((doubled.len(), given_up.len()), (grid.len(), grid.len()));
        assert!(grid.iter().all(|(k, v)| doubled.get(k) == Some(&(2.0 * v)) && given_up.get(k) == Some(&(2.0 * v))));
        assert_eq!(given_up.memory_bytes(), doubled.memory_bytes());
    }
}
