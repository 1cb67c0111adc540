//! # neuvolex-features-burn
//!
//! The NeuVolEx INR expressed with burn tensors, parameter for parameter the same as the fused
//! CPU engine in `neuvolex-features`: the hash-grid gather is burn's differentiable `select`
//! over the flat table (so gradients flow into the table through burn's autodiff), followed by
//! the structural encoder, FiLM, the residual MLP and the heads. It serves two purposes:
//!
//! - the **correctness reference**: tests compare its loss and autodiff gradients with the fused
//!   engine's hand-written backward pass on every ablation;
//! - the **route to GPU backends**: the same code runs on any burn `Device` (`Device::flex()` in
//!   the default build; `--features wgpu` adds burn's wgpu backend).

#![warn(missing_docs)]

use burn_tensor::activation::relu;
use burn_tensor::{Device, Int, Tensor, TensorData};
use neuvolex_features::model::{InrModel, LayerSpec};

/// One dense layer as burn tensors: weights `out x in`, optional bias.
struct Layer {
    spec: LayerSpec,
    w: Tensor<2>,
    b: Option<Tensor<1>>,
}

/// The model as burn tensors (leaves that require gradients).
pub struct BurnInr<'m> {
    model: &'m InrModel,
    device: Device,
    table: Tensor<2>,
    layers: Vec<Layer>,
}

/// Loss and gradients from burn's autodiff, in the fused engine's parameter layouts.
#[derive(Debug, Clone)]
pub struct BurnGrads {
    /// The loss.
    pub loss: f32,
    /// Heads' outputs (`n x heads`).
    pub outputs: Vec<f32>,
    /// Gradient of the dense parameters (the fused engine's flat layout).
    pub dense: Vec<f32>,
    /// Gradient of the table (level-major, like the fused engine's table).
    pub table: Vec<f32>,
}

fn all_layers(m: &InrModel) -> Vec<LayerSpec> {
    let l = &m.layout;
    let mut v = l.structural.clone();
    v.extend(l.film);
    v.extend(l.main.iter().copied());
    v.push(l.proj);
    v.push(l.head);
    v
}

impl<'m> BurnInr<'m> {
    /// Copies the parameters of `model` onto `device` (use `Device::flex().autodiff()` for gradients).
    pub fn new(model: &'m InrModel, device: Device) -> Self {
        let f = model.grid.f;
        let table = Tensor::<2>::from_data(
            TensorData::new(model.table.clone(), [model.table.len() / f, f]),
            &device,
        )
        .require_grad();
        let layers = all_layers(model)
            .into_iter()
            .map(|spec| {
                let w = model.dense[spec.w..spec.w + spec.out * spec.inp].to_vec();
                let w = Tensor::<2>::from_data(TensorData::new(w, [spec.out, spec.inp]), &device)
                    .require_grad();
                let b = spec.b.map(|o| {
                    Tensor::<1>::from_data(
                        TensorData::new(model.dense[o..o + spec.out].to_vec(), [spec.out]),
                        &device,
                    )
                    .require_grad()
                });
                Layer { spec, w, b }
            })
            .collect();
        BurnInr {
            model,
            device,
            table,
            layers,
        }
    }

    fn layer(&self, spec: &LayerSpec) -> &Layer {
        self.layers
            .iter()
            .find(|l| l.spec.w == spec.w)
            .expect("layer of this model")
    }

    fn linear(&self, x: Tensor<2>, spec: &LayerSpec) -> Tensor<2> {
        let l = self.layer(spec);
        let y = x.matmul(l.w.clone().transpose());
        match &l.b {
            Some(b) => y + b.clone().unsqueeze_dim::<2>(0),
            None => y,
        }
    }

    /// Forward pass for `n` samples: positions in [0, 1]^3 and `patch^3` values each.
    /// Returns the heads' outputs (`n x heads`) and the last hidden layer.
    pub fn forward(&self, coords: &[[f32; 3]], patches: &[f32]) -> (Tensor<2>, Tensor<2>) {
        let m = self.model;
        let n = coords.len();
        let nl = m.grid.levels.len();
        let f = m.grid.f;
        let (mut idx, mut wts) = (
            Vec::with_capacity(n * nl * 8),
            Vec::with_capacity(n * nl * 8),
        );
        for x in coords {
            for l in 0..nl {
                let (i, w) = m.grid.corners(l, *x);
                idx.extend(i.iter().map(|&e| (l * m.grid.t + e as usize) as i64));
                wts.extend_from_slice(&w);
            }
        }
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [n * nl * 8]), &self.device);
        let wts = Tensor::<2>::from_data(TensorData::new(wts, [n * nl * 8, 1]), &self.device);
        let e = nl * f;
        let pos = (self.table.clone().select(0, idx) * wts)
            .reshape([n * nl, 8, f])
            .sum_dim(1)
            .reshape([n, e]);
        let lay = &m.layout;
        let a = m.cfg.ablation;
        let p3 = m.cfg.patch.pow(3);
        let inp = if a.structural() {
            let patch = Tensor::<2>::from_data(
                TensorData::new(patches[..n * p3].to_vec(), [n, p3]),
                &self.device,
            );
            let s = relu(self.linear(patch, &lay.structural[0]));
            let s = relu(self.linear(s, &lay.structural[1]));
            match &lay.film {
                Some(fl) => {
                    let gb = self.linear(s, fl);
                    let gamma = gb.clone().narrow(1, 0, e);
                    let beta = gb.narrow(1, e, e);
                    pos * gamma.add_scalar(1.0) + beta
                }
                None => Tensor::cat(vec![pos, s], 1),
            }
        } else {
            pos
        };
        let mut h = inp.clone();
        for (k, spec) in lay.main.iter().enumerate() {
            let mut z = self.linear(h, spec);
            if k == lay.residual_at {
                z = z + self.linear(inp.clone(), &lay.proj);
            }
            h = relu(z);
        }
        (self.linear(h.clone(), &lay.head), h)
    }

    /// The training loss for targets `n x targets` ([`InrConfig::targets`]): each output's
    /// mean squared error against its target, weighted by [`InrConfig::head_weights`] (the
    /// paper's weighted MSEs, then the context outputs).
    ///
    /// [`InrConfig::targets`]: neuvolex_features::InrConfig::targets
    /// [`InrConfig::head_weights`]: neuvolex_features::InrConfig::head_weights
    pub fn loss(&self, y: Tensor<2>, targets: &[f32]) -> Tensor<1> {
        let m = self.model;
        let n = y.dims()[0];
        let tw = m.cfg.targets();
        let t = Tensor::<2>::from_data(
            TensorData::new(targets[..n * tw].to_vec(), [n, tw]),
            &self.device,
        );
        let weights = m.cfg.head_weights();
        let mut loss: Option<Tensor<1>> = None;
        for (o, (&ti, &w)) in m.cfg.head_targets().iter().zip(&weights).enumerate() {
            let e = y.clone().narrow(1, o, 1) - t.clone().narrow(1, ti, 1);
            let term = (e.clone() * e).mean().mul_scalar(w);
            loss = Some(match loss {
                None => term,
                Some(l) => l + term,
            });
        }
        loss.expect("the heads have at least one output")
    }

    /// Loss and autodiff gradients for a batch, in the fused engine's layouts.
    pub fn gradients(&self, coords: &[[f32; 3]], patches: &[f32], targets: &[f32]) -> BurnGrads {
        let (y, _) = self.forward(coords, patches);
        let outputs: Vec<f32> = y.to_data().try_to_vec::<f32>().unwrap_or_default();
        let loss = self.loss(y, targets);
        let lv: Vec<f32> = loss.to_data().try_to_vec::<f32>().unwrap_or_default();
        let grads = loss.backward();
        let to_vec = |t: Option<Tensor<2>>| -> Vec<f32> {
            t.map(|t| t.into_data().try_to_vec::<f32>().unwrap_or_default())
                .unwrap_or_default()
        };
        let table = to_vec(self.table.grad(&grads));
        let mut dense = vec![0.0f32; self.model.dense.len()];
        for l in &self.layers {
            let g = to_vec(l.w.grad(&grads));
            if !g.is_empty() {
                dense[l.spec.w..l.spec.w + g.len()].copy_from_slice(&g);
            }
            if let (Some(b), Some(o)) = (&l.b, l.spec.b) {
                if let Some(g) = b.grad(&grads) {
                    let g: Vec<f32> = g.into_data().try_to_vec::<f32>().unwrap_or_default();
                    dense[o..o + g.len()].copy_from_slice(&g);
                }
            }
        }
        BurnGrads {
            loss: lv.first().copied().unwrap_or(f32::NAN),
            outputs,
            dense,
            table,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_features::adam::TableGrad;
    use neuvolex_features::model::SampleRef;
    use neuvolex_features::rng::Rng;
    use neuvolex_features::{Ablation, InrConfig};

    /// The fused engine's hand-written backward equals burn's autodiff, for every ablation,
    /// with and without context outputs.
    #[test]
    fn fused_engine_matches_burn_autodiff() {
        for (ab, ctx) in [
            (Ablation::Base, &[][..]),
            (Ablation::Structural, &[]),
            (Ablation::Film, &[]),
            (Ablation::Full, &[]),
            (Ablation::Full, &[1.0, 2.0, 8.0]),
        ] {
            let cfg = InrConfig {
                context_sigmas: ctx.to_vec(),
                levels: 4,
                log2_table: 9,
                base_resolution: 3,
                finest_resolution: Some(20),
                ablation: ab,
                ..Default::default()
            };
            let mut m = InrModel::new(&cfg, [20, 20, 20], 3);
            let mut r = Rng::new(11);
            m.table.iter_mut().for_each(|v| *v = r.uniform(-0.5, 0.5));
            let n = 40;
            let p3 = cfg.patch.pow(3);
            let coords: Vec<[f32; 3]> = (0..n).map(|_| [r.f32(), r.f32(), r.f32()]).collect();
            let patches: Vec<f32> = (0..n * p3).map(|_| r.uniform(-1.0, 1.0)).collect();
            let tw = cfg.targets();
            let targets: Vec<f32> = (0..n * tw).map(|_| r.uniform(-0.3, 1.0)).collect();
            // Fused engine.
            let mut w = m.work();
            let samples: Vec<SampleRef> = (0..n)
                .map(|i| SampleRef {
                    x: coords[i],
                    patch: &patches[i * p3..(i + 1) * p3],
                    target: &targets[i * tw..(i + 1) * tw],
                })
                .collect();
            m.load(&mut w, &samples);
            m.reset(&mut w);
            m.forward_backward(&mut w, n);
            let mut tg = TableGrad::new(m.grid.levels.len(), m.grid.t, m.grid.f);
            tg.scatter(&[&w]);
            // burn.
            let b = BurnInr::new(&m, Device::flex().autodiff());
            let g = b.gradients(&coords, &patches, &targets);
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 + 1e-3 * a.abs().max(b.abs());
            assert!(
                close(w.loss as f32, g.loss),
                "{ab:?} {ctx:?}: loss {} vs burn {}",
                w.loss,
                g.loss
            );
            for (i, (x, y)) in m.outputs(&w).iter().zip(&g.outputs).enumerate() {
                assert!(close(*x, *y), "{ab:?} {ctx:?}: output {i}: {x} vs {y}");
            }
            for (i, (x, y)) in w.grad.iter().zip(&g.dense).enumerate() {
                assert!(
                    close(*x, *y),
                    "{ab:?} {ctx:?}: dense grad {i}: fused {x} vs burn {y}"
                );
            }
            assert_eq!(tg.g.len(), g.table.len());
            for (i, (x, y)) in tg.g.iter().zip(&g.table).enumerate() {
                assert!(
                    close(*x, *y),
                    "{ab:?} {ctx:?}: table grad {i}: fused {x} vs burn {y}"
                );
            }
        }
    }
}
