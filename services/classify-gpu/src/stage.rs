//! The GPU as `neuvolex-classify`'s [`Accelerator`]: what `neuvolex classify --gpu` passes to
//! [`neuvolex_classify::pipeline::classify_with`]. Per brick, its halo is read and normalised
//! on the host as the CPU does, the filter bank and the forest run on the GPU in one
//! submission, and the u8 probabilities and classes come back; the pipeline writes them as the
//! CPU's results.
//!
//! One brick ([`BrickPredictor::predict`]) runs alone on the device (a lock around the reused
//! buffers of each brick shape); a run of bricks ([`BrickPredictor::predict_stream`]) goes
//! through [`crate::stream`]'s ring of blocks, within the accelerator's GPU memory budget.

use crate::device::{GpuDevice, Tracked};
use crate::error::GpuError;
use crate::filters::{FilterSlot, GpuFilterBank};
use crate::forest::{FeatureLayout, GpuForest, BELOW_TAU};
use crate::stream::{Ring, StreamConfig};
use neuvolex_bricks::{Brick, BrickStore};
use neuvolex_classify::accel::{AccelOptions, AcceleratedBrick, Accelerator, BrickPredictor};
use neuvolex_classify::features::{Component, FeatureSet};
use neuvolex_classify::{ClassifyError, Forest};
use neuvolex_filters::Classic;
use std::collections::hash_map::{Entry, HashMap};
use std::sync::{Arc, Mutex};

/// The feature sets the GPU computes, as `--features` names them.
pub const GPU_FEATURE_SETS: &str = "filters+xyz (the default) or filters";

/// Whether the GPU computes `set`: `Some(xyz)` for `filters` (false) and `filters+xyz` (true).
pub fn gpu_features(set: &FeatureSet) -> Option<bool> {
    match set.0.as_slice() {
        [Component::Classic(Classic::Filters)] => Some(false),
        [Component::Classic(Classic::Filters), Component::Xyz] => Some(true),
        _ => None,
    }
}

/// The error for a feature set the GPU does not compute.
pub fn unsupported_features(set: &FeatureSet) -> String {
    format!(
        "--gpu computes the feature sets {GPU_FEATURE_SETS}, not '{set}'; drop --gpu or choose \
         --features filters+xyz"
    )
}

fn gpu_err(e: GpuError) -> ClassifyError {
    ClassifyError::Input(e.to_string())
}

/// A GPU device as an [`Accelerator`].
#[derive(Debug, Clone)]
pub struct GpuAccelerator {
    dev: Arc<GpuDevice>,
    stream: StreamConfig,
}

impl GpuAccelerator {
    /// Predicts on `dev`, which may be shared with other engines of the process (the INR's
    /// `neuvolex_features_gpu::GpuContext::gpu`, say): one card, one memory account.
    ///
    /// ```no_run
    /// use neuvolex_classify_gpu::{AdapterKind, GpuAccelerator, GpuDevice};
    /// let dev = GpuDevice::new(AdapterKind::Any)?;
    /// let accel = GpuAccelerator::new(dev.clone());
    /// assert!(std::sync::Arc::ptr_eq(accel.device(), &dev));
    /// # Ok::<(), neuvolex_classify_gpu::GpuError>(())
    /// ```
    pub fn new(dev: Arc<GpuDevice>) -> Self {
        GpuAccelerator {
            dev,
            stream: StreamConfig::default(),
        }
    }

    /// Streams runs of bricks as `cfg` says (blocks, ring depth, GPU memory budget).
    pub fn with_stream(mut self, cfg: StreamConfig) -> Self {
        self.stream = cfg;
        self
    }

    /// How runs of bricks stream.
    pub fn stream(&self) -> &StreamConfig {
        &self.stream
    }

    /// The device it predicts on.
    pub fn device(&self) -> &Arc<GpuDevice> {
        &self.dev
    }
}

impl Accelerator for GpuAccelerator {
    fn describe(&self) -> String {
        self.dev.describe()
    }

    fn prepare(
        &self,
        store: Arc<BrickStore>,
        set: &FeatureSet,
        forest: &Forest,
        opts: &AccelOptions,
    ) -> Result<Box<dyn BrickPredictor>, ClassifyError> {
        let xyz =
            gpu_features(set).ok_or_else(|| ClassifyError::Input(unsupported_features(set)))?;
        let bank = GpuFilterBank::new(self.dev.clone(), xyz).map_err(gpu_err)?;
        let gf = GpuForest::new(self.dev.clone(), forest)
            .map_err(gpu_err)?
            .with_tau(opts.tau)
            .with_f16(opts.f16_features);
        if gf.features() != bank.channels() {
            return Err(ClassifyError::Input(format!(
                "the forest takes {} features, the GPU's '{set}' gives {}",
                gf.features(),
                bank.channels()
            )));
        }
        Ok(Box::new(GpuPredictor {
            store,
            halo: set.halo(),
            bank,
            forest: gf,
            slots: Mutex::default(),
            stream: self.stream,
            ring: Mutex::default(),
        }))
    }
}

/// The buffers of one brick shape: the filter bank's and the forest's output.
struct Slot {
    filt: FilterSlot,
    out: Tracked,
}

/// A forest and the filter bank on the GPU over one store's bricks.
struct GpuPredictor {
    store: Arc<BrickStore>,
    halo: usize,
    bank: GpuFilterBank,
    forest: GpuForest,
    slots: Mutex<HashMap<[usize; 3], Slot>>,
    stream: StreamConfig,
    /// The ring of blocks, made by the first stream and kept for the next.
    ring: Mutex<Option<Ring>>,
}

impl GpuPredictor {
    fn run(&self, b: &Brick) -> Result<AcceleratedBrick, GpuError> {
        let hb = self
            .store
            .read_halo(b, self.halo)
            .map_err(|e| GpuError::Input(format!("brick {:?}: {e}", b.index)))?;
        let norm = self.store.normaliser();
        let dims = self.store.info().dims;
        let n = b.voxels();
        let dev = self.bank.device();
        let mut slots = self.slots.lock().unwrap_or_else(|p| p.into_inner());
        let s = match slots.entry(b.size) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => {
                let filt = self.bank.slot(b.size, self.halo)?;
                let out = dev.buffer(
                    "forest out",
                    self.forest.output_bytes(n),
                    wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                )?;
                e.insert(Slot { filt, out })
            }
        };
        let mut enc = dev.device.create_command_encoder(&Default::default());
        self.bank.encode(&s.filt, &mut enc, &hb, &norm, dims)?;
        self.forest.encode(
            &mut enc,
            s.filt.features(),
            FeatureLayout::planes(n),
            n,
            &s.out,
        )?;
        dev.queue.submit([enc.finish()]);
        let bytes = dev.read(&s.out, self.forest.output_bytes(n))?;
        let c = self.forest.classes();
        let lo = self.forest.labels_offset(n) as usize;
        Ok(AcceleratedBrick {
            probs: bytes[..n * c].to_vec(),
            classes: classes(bytes[lo..lo + n].to_vec()),
        })
    }

    fn stream(
        &self,
        bricks: &[Brick],
        on: &mut dyn FnMut(&Brick, AcceleratedBrick) -> bool,
    ) -> Result<(), GpuError> {
        let mut ring = self.ring.lock().unwrap_or_else(|p| p.into_inner());
        let ring = match &mut *ring {
            Some(r) => r,
            None => ring.insert(Ring::new(
                &self.bank,
                &self.forest,
                &self.store,
                self.halo,
                &self.stream,
            )?),
        };
        let norm = self.store.normaliser();
        crate::stream::run(
            ring,
            &self.bank,
            &self.forest,
            &self.store,
            self.halo,
            &norm,
            bricks,
            &mut |out| {
                out.into_iter().all(|(b, probs, cls)| {
                    on(
                        &b,
                        AcceleratedBrick {
                            probs,
                            classes: classes(cls),
                        },
                    )
                })
            },
        )
    }
}

/// The GPU forest's class codes as [`AcceleratedBrick::classes`] holds them.
fn classes(mut codes: Vec<u8>) -> Vec<u8> {
    for k in &mut codes {
        if *k == BELOW_TAU {
            *k = neuvolex_classify::accel::BELOW_TAU;
        }
    }
    codes
}

impl BrickPredictor for GpuPredictor {
    fn predict(&self, b: &Brick) -> Result<AcceleratedBrick, ClassifyError> {
        self.run(b)
            .map_err(|e| ClassifyError::Input(format!("GPU, brick {:?}: {e}", b.index)))
    }

    fn predict_stream(
        &self,
        bricks: &[Brick],
        on: &mut dyn FnMut(&Brick, AcceleratedBrick) -> bool,
    ) -> Result<(), ClassifyError> {
        self.stream(bricks, on)
            .map_err(|e| ClassifyError::Input(format!("GPU: {e}")))
    }
}
