//! The CPU renderer: schedules the pure per-brick march over bricks in visibility order, with a
//! bounded brick cache, empty-space skipping, progressive passes and re-rendering of only the
//! pixels that changed bricks affect.

use crate::image::Image;
use crate::march::{Accum, CellMap, Frame, Mode, Rays, RenderParams};
use crate::source::{BrickSource, RenderBrick, APRON};
use crate::tf::Luts;
use crate::Result;
use neuvolex_bricks::lru::Lru;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;

/// Bricks loaded in parallel ahead of marching: each batch costs two parallel sections (the
/// loading and the march), and waking the pool for each is a fixed cost of a frame (32 bricks a
/// batch measured about 5 % faster than 16 on the bonsai at 256^2, 2 cores).
const PREFETCH: usize = 32;

/// What a frame cost.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderStats {
    /// Bricks in the grid.
    pub bricks: usize,
    /// Bricks skipped without loading (off screen, empty by range, or fully occluded).
    pub skipped_unloaded: usize,
    /// Bricks loaded but skipped as invisible under the transfer function.
    pub skipped_empty: usize,
    /// Bricks marched.
    pub marched: usize,
    /// Samples taken.
    pub samples: u64,
    /// Pixels rendered.
    pub pixels: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// One pass of a progressive render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pass {
    /// 0-based pass number.
    pub index: usize,
    /// Passes in all.
    pub of: usize,
    /// Resolution divisor of this pass (1 = full).
    pub divisor: usize,
    /// Its cost.
    pub stats: RenderStats,
}

struct Last {
    params: RenderParams,
    luts: Luts,
    acc: Vec<Accum>,
}

/// The key of a render brick in a [`BrickCache`]: the owning renderer, the brick, and whether
/// it holds probabilities.
pub type BrickKey = (u64, [usize; 3], bool);

/// Render bricks of one or several renderers under one byte budget (a server shares one
/// between all its sessions: [`Renderer::with_cache`]).
pub type BrickCache = Lru<BrickKey, Arc<RenderBrick>>;

/// Polled between batches of bricks and before each image row of a batch: `true` stops the
/// frame with [`crate::RenderError::Cancelled`].
pub type CancelPoll = Arc<dyn Fn() -> bool + Send + Sync>;

/// A kept cell map and the brick it was made from.
type KeptMap = (Weak<RenderBrick>, Option<Arc<CellMap>>);

/// The cell maps of bricks under one mode and set of tables (a frame's empty-space skipping
/// inside its bricks), kept from frame to frame while those stay: a new camera does not make
/// them again. Each is held with the brick it was made from, and is used only with that brick
/// (a brick loaded again, or changed, gets a new map).
#[derive(Default)]
struct CellMaps {
    /// The mode and tables the maps were made under.
    key: Option<(Mode, Luts)>,
    /// Per brick (index, with probabilities): the brick, and its map (`None`: nothing in it
    /// can be visible).
    maps: HashMap<([usize; 3], bool), KeptMap>,
}

/// A CPU renderer over a brick source, keeping the last frame for incremental updates.
pub struct Renderer<S: BrickSource> {
    source: S,
    cache: Arc<BrickCache>,
    owner: u64,
    cancel: Option<CancelPoll>,
    last: Option<Last>,
    stats: RenderStats,
    /// The last frame's rays, for the next frame of the same view.
    rays: Option<Arc<Rays>>,
    /// Cell maps kept from frame to frame.
    cell_maps: Mutex<CellMaps>,
}

impl<S: BrickSource> Renderer<S> {
    /// A renderer caching at most `cache_bytes` of bricks.
    pub fn new(source: S, cache_bytes: usize) -> Self {
        Self::with_cache(source, Arc::new(Lru::new(cache_bytes)), 0)
    }

    /// A renderer keeping its bricks in `cache`, shared with other renderers under one budget,
    /// as `owner` (each sharing renderer needs its own; [`Self::forget`] drops its bricks).
    pub fn with_cache(source: S, cache: Arc<BrickCache>, owner: u64) -> Self {
        Renderer {
            source,
            cache,
            owner,
            cancel: None,
            last: None,
            stats: RenderStats::default(),
            rays: None,
            cell_maps: Mutex::default(),
        }
    }

    /// Drops this renderer's bricks from its cache (a shared cache keeps the others').
    pub fn forget(&self) {
        let owner = self.owner;
        self.cache.retain(|k| k.0 != owner);
        self.maps().maps.clear();
    }

    /// The kept cell maps (a poisoned lock only means a panic elsewhere: the maps stay whole,
    /// each inserted at once).
    fn maps(&self) -> std::sync::MutexGuard<'_, CellMaps> {
        self.cell_maps.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The cell map of brick `b` (loaded for `index`, with probabilities when `probs`) under
    /// `frame`'s mode and tables: the kept one when it was made from this brick, else made
    /// and kept. `None` when nothing in the brick can be visible.
    fn cell_map(
        &self,
        frame: &Frame<'_>,
        index: [usize; 3],
        probs: bool,
        b: &Arc<RenderBrick>,
    ) -> Option<Arc<CellMap>> {
        if let Some((w, m)) = self.maps().maps.get(&(index, probs)) {
            // The held Weak keeps the old brick's allocation, so an equal address is the
            // same brick.
            if std::ptr::eq(w.as_ptr(), Arc::as_ptr(b)) {
                return m.clone();
            }
        }
        let m = frame.visible(b).then(|| Arc::new(frame.cell_map(b)));
        self.maps()
            .maps
            .insert((index, probs), (Arc::downgrade(b), m.clone()));
        m
    }

    /// Polls `cancel` between batches of bricks and image rows from now on (`None`: never
    /// cancelled); a cancelled frame or update returns [`crate::RenderError::Cancelled`], and
    /// the next call renders from scratch.
    pub fn set_cancel(&mut self, cancel: Option<CancelPoll>) {
        self.cancel = cancel;
    }

    /// The source.
    pub fn source(&self) -> &S {
        &self.source
    }

    /// The source, to change it; follow with [`Self::update_bricks`] for what changed.
    pub fn source_mut(&mut self) -> &mut S {
        &mut self.source
    }

    /// Cost of the last render or update.
    pub fn stats(&self) -> RenderStats {
        self.stats
    }

    /// Renders a frame.
    pub fn render(&mut self, params: &RenderParams, luts: &Luts) -> Result<Image> {
        let frame = Frame::new(*params, self.source.geom(), luts)?.reusing_rays(self.rays.take());
        self.rays = Some(frame.rays());
        let mut acc = vec![[0.0f32; 4]; params.width * params.height];
        let stats = self.composite(&frame, &mut acc, None)?;
        let img = finish(&frame, &acc);
        self.stats = stats;
        self.last = Some(Last {
            params: *params,
            luts: luts.clone(),
            acc,
        });
        Ok(img)
    }

    /// Renders at `divisors` of the full resolution in turn (e.g. `[4, 2, 1]`), calling
    /// `on_pass` with each image; coarse passes also step `divisor` times further (at most 2
    /// voxels). The last pass is kept for [`Self::update_bricks`].
    pub fn progressive(
        &mut self,
        params: &RenderParams,
        luts: &Luts,
        divisors: &[usize],
        mut on_pass: impl FnMut(Pass, &Image),
    ) -> Result<Image> {
        let mut out = None;
        for (n, &d) in divisors.iter().enumerate() {
            let d = d.max(1);
            let mut p = *params;
            p.width = params.width.div_ceil(d);
            p.height = params.height.div_ceil(d);
            if d > 1 {
                p.step = (params.step * d as f32).min(2.0f32.max(params.step));
            }
            let img = self.render(&p, luts)?;
            on_pass(
                Pass {
                    index: n,
                    of: divisors.len(),
                    divisor: d,
                    stats: self.stats,
                },
                &img,
            );
            out = Some(img);
        }
        out.ok_or_else(|| crate::RenderError::Param("no progressive passes".into()))
    }

    /// After the data of `changed` bricks changed (new probabilities, a new scribble), updates
    /// the last frame by re-rendering only the pixels whose rays read those bricks, and
    /// returns it (`None` when nothing was rendered yet). The result equals a full render.
    pub fn update_bricks(&mut self, changed: &[[usize; 3]]) -> Result<Option<Image>> {
        self.invalidate(changed)?;
        let Some(last) = self.last.take() else {
            return Ok(None);
        };
        let frame =
            Frame::new(last.params, self.source.geom(), &last.luts)?.reusing_rays(self.rays.take());
        self.rays = Some(frame.rays());
        let (w, h) = (last.params.width, last.params.height);
        let mut mask = vec![false; w * h];
        for c in changed {
            if let Some(r) = frame.footprint(*c, APRON as f32 + 0.5) {
                for j in r[2]..r[3] {
                    mask[j * w + r[0]..j * w + r[1]].fill(true);
                }
            }
        }
        let mut acc = last.acc;
        for (a, &m) in acc.iter_mut().zip(&mask) {
            if m {
                *a = [0.0; 4];
            }
        }
        let stats = self.composite(&frame, &mut acc, Some(&mask))?;
        let img = finish(&frame, &acc);
        self.stats = stats;
        self.last = Some(Last {
            params: last.params,
            luts: last.luts.clone(),
            acc,
        });
        Ok(Some(img))
    }

    /// Forgets the cached copies of `changed` bricks (and of their neighbours, whose aprons
    /// hold their voxels) after their data changed, without rendering; the last frame is kept
    /// as it was.
    pub fn invalidate(&mut self, changed: &[[usize; 3]]) -> Result<()> {
        let g = self.source.geom().grid();
        let mut stale = Vec::new();
        for c in changed {
            if (0..3).any(|k| c[k] >= g[k]) {
                return Err(crate::RenderError::Input(format!(
                    "changed brick {c:?} outside the {g:?} grid"
                )));
            }
            // Its voxels sit in the aprons of its neighbours too.
            stale.extend(crate::source::neighbourhood(*c, g));
        }
        self.source.invalidate(changed);
        let mut maps = self.maps();
        for n in &stale {
            self.cache.remove(&(self.owner, *n, false));
            self.cache.remove(&(self.owner, *n, true));
            maps.maps.remove(&(*n, false));
            maps.maps.remove(&(*n, true));
        }
        Ok(())
    }

    /// Brick `index` through the cache; with its central differences made when `shaded` (so
    /// the cache counts them).
    fn load(&self, index: [usize; 3], probs: bool, shaded: bool) -> Result<Arc<RenderBrick>> {
        self.cache
            .get_or_try_insert(&(self.owner, index, probs), || {
                let b = self.source.load(index, probs)?;
                if shaded {
                    b.differences();
                }
                let cost = b.bytes();
                Ok((Arc::new(b), cost))
            })
    }

    /// Composites every brick, front to back, into `acc` (only masked pixels if a mask is
    /// given).
    fn composite(
        &self,
        frame: &Frame<'_>,
        acc: &mut [Accum],
        mask: Option<&[bool]>,
    ) -> Result<RenderStats> {
        let t = Instant::now();
        let w = frame.params.width;
        let probs = frame.params.mode.needs_probs();
        let shaded = frame.params.shading.is_some();
        {
            // Maps made under other tables or another mode are dropped.
            let mut maps = self.maps();
            let key = (frame.params.mode, frame.luts);
            if maps.key.as_ref().is_none_or(|(m, l)| (*m, l) != key) {
                maps.maps.clear();
                maps.key = Some((key.0, key.1.clone()));
            }
        }
        let order = frame.ordered_bricks();
        let mut stats = RenderStats {
            bricks: order.len(),
            pixels: mask.map_or(acc.len(), |m| m.iter().filter(|&&x| x).count()),
            ..Default::default()
        };
        let samples = AtomicU64::new(0);
        let cancelled = AtomicBool::new(false);
        let ert = frame.params.ert;
        let mut queue: Vec<([usize; 3], [usize; 4])> = Vec::with_capacity(PREFETCH);
        let mut pending = order.into_iter().peekable();
        while pending.peek().is_some() {
            if self.cancel.as_ref().is_some_and(|c| c()) {
                return Err(crate::RenderError::Cancelled);
            }
            // The next bricks that need loading: on screen, possibly visible, not occluded.
            queue.clear();
            for i in pending.by_ref() {
                let Some(r) = frame.footprint(i, 0.0) else {
                    stats.skipped_unloaded += 1;
                    continue;
                };
                if let Some(range) = self.source.coarse_range(i) {
                    if !frame.coarse_visible(range) {
                        stats.skipped_unloaded += 1;
                        continue;
                    }
                }
                let open = (r[2]..r[3]).any(|j| {
                    (r[0]..r[1]).any(|x| {
                        let p = j * w + x;
                        acc[p][3] < ert && mask.is_none_or(|m| m[p])
                    })
                });
                if !open {
                    stats.skipped_unloaded += 1;
                    continue;
                }
                queue.push((i, r));
                if queue.len() == PREFETCH {
                    break;
                }
            }
            // Loaded in parallel, each with its cells' visibility when it is visible at all.
            type Loaded = Result<(Arc<RenderBrick>, Option<Arc<CellMap>>)>;
            let loaded: Vec<Loaded> = queue
                .par_iter()
                .map(|(i, _)| {
                    let b = self.load(*i, probs, shaded)?;
                    let cells = self.cell_map(frame, *i, probs, &b);
                    Ok((b, cells))
                })
                .collect();
            // The batch's visible bricks, front to back, with their footprints and cells.
            let mut batch = Vec::with_capacity(queue.len());
            for ((_, r), b) in queue.iter().zip(loaded) {
                let (b, cells) = b?;
                let Some(cells) = cells else {
                    stats.skipped_empty += 1;
                    continue;
                };
                stats.marched += 1;
                batch.push((*r, b, cells));
            }
            // One parallel pass over the rows the batch covers: each row marches the bricks
            // whose footprint holds it, in the batch's order, so every pixel composites its
            // bricks front to back as brick-by-brick passes would (the same sums in the same
            // order), with one join per batch instead of one per brick.
            let (Some(top), Some(bottom)) = (
                batch.iter().map(|(r, _, _)| r[2]).min(),
                batch.iter().map(|(r, _, _)| r[3]).max(),
            ) else {
                continue;
            };
            // The cancel poll also runs row by row: a batch of a large image is long.
            acc[top * w..bottom * w]
                .par_chunks_mut(w)
                .enumerate()
                .with_min_len(2)
                .for_each(|(n, row)| {
                    if cancelled.load(Ordering::Relaxed) {
                        return;
                    }
                    if self.cancel.as_ref().is_some_and(|c| c()) {
                        cancelled.store(true, Ordering::Relaxed);
                        return;
                    }
                    let j = top + n;
                    let m = mask.map(|m| &m[j * w..(j + 1) * w]);
                    let mut s = 0;
                    for (r, b, cells) in &batch {
                        if (r[2]..r[3]).contains(&j) {
                            s += frame.march_row(b, j, r[0]..r[1], row, m, cells);
                        }
                    }
                    samples.fetch_add(s, Ordering::Relaxed);
                });
            if cancelled.load(Ordering::Relaxed) {
                return Err(crate::RenderError::Cancelled);
            }
        }
        stats.samples = samples.into_inner();
        stats.seconds = t.elapsed().as_secs_f64();
        tracing::debug!(?stats, "frame");
        Ok(stats)
    }
}

/// Composites the background under the accumulated colour.
fn finish(frame: &Frame<'_>, acc: &[Accum]) -> Image {
    let bg = frame.params.background;
    Image {
        width: frame.params.width,
        height: frame.params.height,
        rgb: acc
            .iter()
            .map(|a| {
                [
                    a[0] + (1.0 - a[3]) * bg[0],
                    a[1] + (1.0 - a[3]) * bg[1],
                    a[2] + (1.0 - a[3]) * bg[2],
                ]
            })
            .collect(),
        alpha: acc.iter().map(|a| a[3]).collect(),
    }
}
