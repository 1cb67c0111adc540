//! Bricks streamed through the GPU beyond its memory (issue 49, part 4): neighbouring bricks
//! are grouped into blocks that share one halo ([`plan_blocks`]), a producer thread reads and
//! normalises the next blocks on the host while the device filters and predicts the current
//! ones, and a fixed ring of device buffers ([`StreamConfig::in_flight`] blocks, sized to
//! [`StreamConfig::budget`]) bounds GPU memory whatever the volume's size. Results come back
//! block by block, in the order of each block's first brick in the order asked for, so a caller
//! that puts the stroked slice's bricks first sees them first.
//!
//! The computation per block is the one per brick ([`crate::GpuFilterBank`], then
//! [`crate::GpuForest`]): a block is one larger brick whose halo is read edge-clamped
//! ([`neuvolex_bricks::BrickStore::read_padded`]), and the filter bank of a voxel reads only
//! its halo, so a brick predicted in a block gives what it gives alone (the tests check this).

use crate::device::{GpuDevice, Tracked};
use crate::error::{GpuError, Result};
use crate::filters::{FilterSlot, GpuFilterBank};
use crate::forest::{FeatureLayout, GpuForest};
use neuvolex_bricks::derived::Normaliser;
use neuvolex_bricks::{Brick, BrickStore};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::mpsc::sync_channel;

/// GPU memory the ring and the forest may hold together by default (2 GiB): two blocks of
/// 128^3 voxels with the filter bank's halo (about 730 MiB each) and a forest.
pub const DEFAULT_BUDGET: u64 = 2 << 30;

/// How bricks stream through the GPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamConfig {
    /// Blocks on the device at once (the ring's depth; at least 1): while one block's results
    /// are read back, the next is computed.
    pub in_flight: usize,
    /// GPU bytes the ring and the forest may hold together; blocks shrink (to one brick at
    /// the least) and the ring gets shallower to stay within it.
    pub budget: u64,
    /// Voxels along each side of a block, rounded down to whole bricks (at least one brick):
    /// bricks of a block share one halo, so larger blocks compute fewer halo voxels.
    pub block: usize,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            in_flight: 2,
            budget: DEFAULT_BUDGET,
            block: 128,
        }
    }
}

/// Neighbouring bricks computed as one: the core `origin..origin+size` (inside the grid)
/// covers every brick of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Block {
    /// The core's first voxel (x, y, z).
    pub origin: [usize; 3],
    /// The bricks it predicts, in the order asked for.
    pub bricks: Vec<Brick>,
}

/// The bricks of `order` grouped into blocks of up to `per` bricks a side (aligned to
/// multiples of `per` bricks), in the order of each block's first brick in `order`; every
/// block's core is `size` voxels (the returned shape: `per` bricks of `brick` voxels a side,
/// or the grid's size where that is smaller), placed at its bricks and moved back from the
/// grid's far end so that it lies inside the grid.
pub fn plan_blocks(
    order: &[Brick],
    brick: usize,
    dims: [usize; 3],
    per: usize,
) -> (Vec<Block>, [usize; 3]) {
    let per = per.max(1);
    let size = dims.map(|d| (per * brick).min(d));
    let mut at: HashMap<[usize; 3], usize> = HashMap::new();
    let mut blocks: Vec<Block> = Vec::new();
    for b in order {
        let key = b.index.map(|i| i / per);
        let k = *at.entry(key).or_insert_with(|| {
            blocks.push(Block {
                origin: [0; 3],
                bricks: Vec::new(),
            });
            blocks.len() - 1
        });
        blocks[k].bricks.push(*b);
    }
    for blk in &mut blocks {
        blk.origin = std::array::from_fn(|a| {
            let lo = blk.bricks.iter().map(|b| b.origin[a]).min().unwrap_or(0);
            lo.min(dims[a] - size[a])
        });
    }
    (blocks, size)
}

/// One block's device buffers: the filter bank's, the forest's output and its staging copy.
struct Slot {
    filt: FilterSlot,
    out: Tracked,
    staging: Tracked,
}

/// The ring: `slots` of one block shape.
pub(crate) struct Ring {
    slots: Vec<Slot>,
    per: usize,
    size: [usize; 3],
}

impl Ring {
    /// GPU bytes of one slot of blocks of `size`, with room for the small uniform, tap and
    /// argument buffers of a dispatch.
    fn slot_bytes(bank: &GpuFilterBank, forest: &GpuForest, size: [usize; 3], halo: usize) -> u64 {
        let core: usize = size.iter().product();
        bank.slot_bytes(size, halo) + 2 * forest.output_bytes(core) + SMALL
    }

    /// The largest blocks (at most `cfg.block` voxels a side) whose slot, with the forest,
    /// fits `cfg.budget` and the device's bindings, and as many slots as fit (at most
    /// `cfg.in_flight`); an error naming the budget where one brick's slot does not fit.
    pub(crate) fn new(
        bank: &GpuFilterBank,
        forest: &GpuForest,
        store: &BrickStore,
        halo: usize,
        cfg: &StreamConfig,
    ) -> Result<Ring> {
        let dev = bank.device();
        let (brick, dims) = (store.info().brick, store.info().dims);
        let fits = |size: [usize; 3]| -> Option<u64> {
            let p: u64 = size.iter().map(|&s| (s + 2 * halo) as u64).product();
            let core: u64 = size.iter().map(|&s| s as u64).product();
            let binding = dev.max_binding();
            // The filter arena (13 grids) and the feature planes are single bindings.
            if 13 * p * 4 > binding || bank.channels() as u64 * core * 4 > binding {
                return None;
            }
            let slot = Self::slot_bytes(bank, forest, size, halo);
            (forest.bytes() + slot <= cfg.budget).then_some(slot)
        };
        let mut per = (cfg.block / brick).max(1);
        let (size, slot) = loop {
            let size = dims.map(|d| (per * brick).min(d));
            if let Some(slot) = fits(size) {
                break (size, slot);
            }
            if per == 1 {
                let need = forest.bytes() + Self::slot_bytes(bank, forest, size, halo);
                return Err(GpuError::Input(format!(
                    "one brick of {size:?} voxels needs {:.0} MiB of GPU memory with the forest, \
                     over the budget of {:.0} MiB (or past the device's largest binding of {:.0} \
                     MiB)",
                    need as f64 / MIB,
                    cfg.budget as f64 / MIB,
                    dev.max_binding() as f64 / MIB
                )));
            }
            per /= 2;
        };
        let depth =
            (((cfg.budget - forest.bytes()) / slot) as usize).clamp(1, cfg.in_flight.max(1));
        let core: usize = size.iter().product();
        let obytes = forest.output_bytes(core);
        let slots = (0..depth)
            .map(|_| -> Result<Slot> {
                Ok(Slot {
                    filt: bank.slot(size, halo)?,
                    out: dev.buffer(
                        "forest out",
                        obytes,
                        wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                    )?,
                    staging: dev.buffer(
                        "forest staging",
                        obytes,
                        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    )?,
                })
            })
            .collect::<Result<_>>()?;
        tracing::debug!(
            blocks = ?size,
            depth,
            slot_mib = slot as f64 / MIB,
            "GPU ring"
        );
        Ok(Ring { slots, per, size })
    }

    /// Blocks in flight.
    pub(crate) fn depth(&self) -> usize {
        self.slots.len()
    }
}

const MIB: f64 = (1u64 << 20) as f64;

/// Bytes reserved per slot for the filter bank's uniforms and taps and the forest's arguments.
const SMALL: u64 = 1 << 20;

/// What a block gives back: per brick, its u8 probabilities (`voxels x classes`) and classes
/// (the forest's raw codes), x fastest within the brick.
pub(crate) type BlockOut = Vec<(Brick, Vec<u8>, Vec<u8>)>;

/// Streams `order`'s bricks through `ring`: blocks read and normalised on a producer thread
/// (a few at once in parallel), filtered and predicted on the device, read back one ring turn
/// later; `on` gets each block's bricks and stops the stream by returning false.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run(
    ring: &Ring,
    bank: &GpuFilterBank,
    forest: &GpuForest,
    store: &BrickStore,
    halo: usize,
    norm: &Normaliser,
    order: &[Brick],
    on: &mut dyn FnMut(BlockOut) -> bool,
) -> Result<()> {
    let dev: &GpuDevice = bank.device();
    let info = store.info();
    let dims = info.dims;
    let (blocks, size) = plan_blocks(order, info.brick, dims, ring.per);
    debug_assert_eq!(size, ring.size);
    let core: usize = size.iter().product();
    let c = forest.classes();
    let obytes = forest.output_bytes(core);
    let lo = forest.labels_offset(core) as usize;
    let depth = ring.depth();
    // Blocks read at once by the producer: enough to keep a many-core host ahead of the device,
    // few enough to bound host memory (each is a padded f32 grid).
    let batch = rayon::current_num_threads().clamp(1, 4);
    let read = |blk: &Block| -> Result<Vec<f32>> {
        let mut h = store
            .read_padded(blk.origin, size, halo)
            .map_err(|e| GpuError::Input(format!("block at {:?}: {e}", blk.origin)))?;
        for v in h.data.iter_mut() {
            *v = norm.apply(*v);
        }
        Ok(h.data)
    };
    let split = |blk: &Block, bytes: &[u8]| -> BlockOut {
        blk.bricks
            .iter()
            .map(|b| {
                let n = b.voxels();
                let (mut probs, mut classes) = (Vec::with_capacity(n * c), Vec::with_capacity(n));
                let off = std::array::from_fn::<usize, 3, _>(|a| b.origin[a] - blk.origin[a]);
                for z in 0..b.size[2] {
                    for y in 0..b.size[1] {
                        let v = ((off[2] + z) * size[1] + off[1] + y) * size[0] + off[0];
                        probs.extend_from_slice(&bytes[v * c..(v + b.size[0]) * c]);
                        classes.extend_from_slice(&bytes[lo + v..lo + v + b.size[0]]);
                    }
                }
                (*b, probs, classes)
            })
            .collect()
    };
    let (tx, rx) = sync_channel::<Result<Vec<f32>>>(depth);
    std::thread::scope(|sc| -> Result<()> {
        // Owned here, so that stopping early drops it and the producer ends.
        let rx = rx;
        let blocks = &blocks;
        sc.spawn(move || {
            for part in blocks.chunks(batch) {
                let grids: Vec<Result<Vec<f32>>> = part.par_iter().map(read).collect();
                for g in grids {
                    let stop = g.is_err();
                    if tx.send(g).is_err() || stop {
                        return;
                    }
                }
            }
        });
        let mut pending: Vec<Option<(usize, wgpu::SubmissionIndex)>> =
            (0..depth).map(|_| None).collect();
        let mut collect = |si: usize,
                           pending: &mut Vec<Option<(usize, wgpu::SubmissionIndex)>>|
         -> Result<bool> {
            match pending[si].take() {
                Some((k, idx)) => {
                    let bytes = dev.map_read_after(&ring.slots[si].staging, obytes, Some(idx))?;
                    Ok(on(split(&blocks[k], &bytes)))
                }
                None => Ok(true),
            }
        };
        for (k, grid) in rx.iter().enumerate() {
            let grid = grid?;
            let si = k % depth;
            if !collect(si, &mut pending)? {
                return Ok(());
            }
            let slot = &ring.slots[si];
            let mut enc = dev.device.create_command_encoder(&Default::default());
            bank.encode_normalised(&slot.filt, &mut enc, &grid, blocks[k].origin, dims)?;
            forest.encode(
                &mut enc,
                slot.filt.features(),
                FeatureLayout::planes(core),
                core,
                &slot.out,
            )?;
            enc.copy_buffer_to_buffer(&slot.out, 0, &slot.staging, 0, obytes);
            pending[si] = Some((k, dev.queue.submit([enc.finish()])));
        }
        // The last turn of the ring, oldest first.
        let next = blocks.len() % depth;
        for j in 0..depth {
            if !collect((next + j) % depth, &mut pending)? {
                return Ok(());
            }
        }
        Ok(dev.check()?)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bricks of a `dims` grid in bricks of `b`, z-major.
    fn grid(dims: [usize; 3], b: usize) -> Vec<Brick> {
        let n = dims.map(|d| d.div_ceil(b));
        let mut v = Vec::new();
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let index = [x, y, z];
                    let origin = index.map(|i| i * b);
                    let size = std::array::from_fn(|a| b.min(dims[a] - origin[a]));
                    v.push(Brick {
                        index,
                        origin,
                        size,
                    });
                }
            }
        }
        v
    }

    #[test]
    fn blocks_cover_each_brick_once_inside_the_grid_in_first_brick_order() {
        let dims = [45, 38, 20];
        let mut order = grid(dims, 8);
        order.reverse();
        for per in [1, 2, 3, 8] {
            let (blocks, size) = plan_blocks(&order, 8, dims, per);
            assert_eq!(size, dims.map(|d| (per * 8).min(d)));
            let flat: Vec<[usize; 3]> = blocks
                .iter()
                .flat_map(|b| b.bricks.iter().map(|b| b.index))
                .collect();
            let mut sorted = flat.clone();
            sorted.sort();
            sorted.dedup();
            assert_eq!(sorted.len(), order.len(), "per {per}: each brick once");
            // A block's place is that of its first brick in the order.
            let firsts: Vec<usize> = blocks
                .iter()
                .map(|b| order.iter().position(|o| o == &b.bricks[0]).unwrap())
                .collect();
            assert!(firsts.windows(2).all(|w| w[0] < w[1]), "per {per}");
            for blk in &blocks {
                let end: [usize; 3] = std::array::from_fn(|a| blk.origin[a] + size[a]);
                assert!((0..3).all(|a| end[a] <= dims[a]), "inside the grid");
                for b in &blk.bricks {
                    assert_eq!(
                        b.index.map(|i| i / per),
                        blk.bricks[0].index.map(|i| i / per)
                    );
                    let covered = (0..3)
                        .all(|a| b.origin[a] >= blk.origin[a] && b.origin[a] + b.size[a] <= end[a]);
                    assert!(
                        covered,
                        "brick {:?} in the block at {:?}",
                        b.index, blk.origin
                    );
                }
            }
        }
        // One brick alone of a far block: its core moves back to end at the grid's end.
        let last = order[0];
        let (blocks, size) = plan_blocks(std::slice::from_ref(&last), 8, dims, 4);
        assert_eq!(size, [32, 32, 20]);
        assert_eq!(blocks[0].origin, [13, 6, 0]);
    }
}
