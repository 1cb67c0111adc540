"""The NeuVolEx INR in plain PyTorch, the reference a user would choose instead of neuvolex,
driven by `benches/inr.rs` (CPU) and `benches/inr_gpu.rs` (CUDA) on the same inputs.

Model: the same architecture and sizes as neuvolex-features (16 levels x 2 features, 2^19
table, base 16, finest = the volume's largest dimension, dense indexing where the level fits
the table, the spatial hash otherwise; structural encoder 125-32-32 -> FiLM; 4x64 MLP with a
residual projection into the third layer; heads for intensity, gradient, mean, std; loss
weights 1, 1 (over the 3 gradient components), 0.5, 0.5; initial parameters: neuvolex's, from
init.f32 (below), so both sides start from the same weights; where that file is absent or does
not fit this model, PyTorch's default layer init and a table uniform in +-1e-4 from seed 0 (the
"ready" line and every round say which: "init"); Adam betas 0.9/0.999, eps 1e-8, lr 1e-3 for the MLPs and 1e-2 for the
table, as neuvolex's `TrainConfig::default()`).

Inputs: the folder `--data` written by the Rust bench from the real volume (CT-Tooth):
  meta.json     dims, patch radius, batch, steps, learning rates, extraction batch
  volume.f32    the volume's normalised intensities padded by the patch radius, as neuvolex's
                tiles hold them (x fastest)
  targets.f32   per voxel: intensity, gradient x/y/z, local mean, local std (neuvolex's tile
                targets), for every voxel of the volume
  order.u32     the training samples, `steps x batch` linear voxel indices: the exact samples
                neuvolex trains on, in the same order
  init.f32      neuvolex's initial parameters (little-endian f32): the hash table, then the
                dense parameters in neuvolex's layout; meta.json's "init" lists every tensor
                as {"name": PyTorch's state_dict name, "offset": in f32 elements, "shape"}
                (nn.Linear's [out, in] weights are neuvolex's row-major out x in), and
                "floats", the file's length. Loaded only if the tensors are exactly this
                model's parameters with these shapes and tile the file (`read_init`).
Everything is loaded onto the device before any timing.

Timed regions (the same on both sides):
  train    `steps` optimiser steps of `batch` samples each: per step, gathering the samples'
           positions, 5^3 patches and targets from the pre-loaded volume (neuvolex's
           `Tile::sample` does the same inside its step), forward, loss, backward, Adam. The
           parameters and the optimiser state are reset to the same initial values before each
           round (outside the timed region).
  extract  the 64-D last hidden layer (and the heads) of every voxel of the volume, forward
           only under no_grad, in fixed-size chunks written into one pre-allocated output.
Untimed: loss and PSNR over every voxel of the volume (PSNR = 10 log10(1 / MSE) of the
intensity head against the intensity target on the normalised range, as neuvolex's `psnr`),
computed from the extraction pass's head outputs; the last step's batch loss.
On CUDA every timed region starts and ends with torch.cuda.synchronize().

Warm-up: every variant compiles and runs its training step (3 steps; 5 with CUDA graphs:
warm-up, capture, replay) and its extraction function (2 chunks, 3 with CUDA graphs, under
no_grad, the mode it is timed in) before the first timed round, so
no compilation, autotuning or CUDA-graph capture falls inside a timed window; the "ready" line
reports each variant's setup seconds and any variant that failed (with the reason).

Variants (`--variants`, comma-separated; a variant that fails to build is reported and left
out, never silently replaced):
  eager            eager model, torch.optim.Adam (default implementation)
  fused            eager model, Adam(fused=True)
  sparse           eager model, sparse table gradients: SparseAdam on the table (touched rows
                   only, the semantics of neuvolex's default lazy table Adam) + Adam on the rest
  compile+fused    torch.compile'd step function (sample gather + forward + loss, and its
                   backward), Adam(fused=True)
  compile+cstep    the same compiled step function, and opt.step compiled with torch.compile
                   (the "compiling the optimizer" recipe)
  sparse+compile   the gather and hash indexing compiled, the sparse table lookup eager, the MLPs
                   and loss compiled; SparseAdam on the table, fused Adam on the rest
  ro+fused         (CUDA) the step function compiled with mode="reduce-overhead" (CUDA graphs),
                   Adam(fused=True)
  ro+cstep         (CUDA) reduce-overhead step function and opt.step compiled with
                   mode="reduce-overhead"
  ma+cstep         (CUDA) mode="max-autotune" (autotuned kernels and CUDA graphs), compiled step
Compiled variants compile their extraction function with the same mode.

Modes:
  --serve  reads JSON lines on stdin, {"variant": NAME} runs one round of that variant and
           prints one JSON line; {"cmd": "quit"} or a bare `quit` line ends. The first stdout line is the "ready"
           line. Only JSON goes to stdout; notes go to stderr.
  default  runs --rounds rounds, the variants alternating, and prints one JSON line per round.
Usage: python3 inr_torch.py --data DIR [--device cpu|cuda] [--threads 2]
       [--variants eager,fused,...] [--serve | --rounds 3]
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np
import torch
import torch.nn as nn

P1, P2 = 2654435761, 805459861


def note(*a):
    print(*a, file=sys.stderr, flush=True)


class HashGrid(nn.Module):
    """All levels and corners in one gather from a flat [L*T, F] table. With sparse=True the
    table is an nn.Embedding with sparse gradients."""

    def __init__(self, levels=16, feats=2, log2t=19, base=16, finest=161, sparse=False):
        super().__init__()
        self.t = 1 << log2t
        b = math.exp((math.log(max(finest, base)) - math.log(base)) / (levels - 1))
        res = [int(math.floor(base * b ** l + 1e-9)) for l in range(levels)]
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32))
        self.register_buffer("resl", torch.tensor(res, dtype=torch.long))
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= self.t for r in res]))
        self.register_buffer("base", torch.arange(levels, dtype=torch.long) * self.t)
        self.register_buffer("off", torch.tensor([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)]))
        self.table = nn.Embedding(levels * self.t, feats, sparse=sparse)
        nn.init.uniform_(self.table.weight, -1e-4, 1e-4)

    def indices(self, x):
        """Table rows [N, L, 8] and trilinear weights [N, L, 8] of the corners around x."""
        p = x.clamp(0, 1)[:, None, :] * self.res[None, :, None]            # [N, L, 3]
        c = torch.minimum(torch.floor(p), (self.res - 1)[None, :, None])
        f = p - c
        v = c.long()[:, :, None, :] + self.off[None, None]                # [N, L, 8, 3]
        r = (self.resl + 1)[None, :, None]
        dense_idx = v[..., 0] + v[..., 1] * r + v[..., 2] * r * r
        hash_idx = (v[..., 0] ^ (v[..., 1] * P1) ^ (v[..., 2] * P2)) & (self.t - 1)
        idx = torch.where(self.dense[None, :, None], dense_idx, hash_idx) + self.base[None, :, None]
        w = torch.where(self.off.bool()[None, None], f[:, :, None, :], 1 - f[:, :, None, :]).prod(-1)
        return idx, w

    @staticmethod
    def blend(w, feats):
        return (w[..., None] * feats).sum(2).flatten(1)

    def forward(self, x):
        idx, w = self.indices(x)
        return self.blend(w, self.table(idx))


class Rest(nn.Module):
    """Everything after the hash grid: structural encoder, FiLM, residual MLP, heads."""

    def __init__(self):
        super().__init__()
        e = 32
        self.struct = nn.Sequential(nn.Linear(125, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU())
        self.film = nn.Linear(32, 2 * e)
        self.m = nn.ModuleList([nn.Linear(e, 64)] + [nn.Linear(64, 64) for _ in range(3)])
        self.proj = nn.Linear(e, 64, bias=False)
        self.head = nn.Linear(64, 6)

    def forward(self, pos, patch):
        gb = self.film(self.struct(patch))
        inp = pos * (gb[:, :32] + 1) + gb[:, 32:]
        h = inp
        for k, layer in enumerate(self.m):
            z = layer(h)
            if k == 2:
                z = z + self.proj(inp)
            h = torch.relu(z)
        return self.head(h), h


class Inr(nn.Module):
    def __init__(self, finest, sparse=False):
        super().__init__()
        self.grid = HashGrid(finest=finest, sparse=sparse)
        self.rest = Rest()

    def forward(self, x, patch):
        return self.rest(self.grid(x), patch)


def loss_fn(y, t):
    return ((y[:, 0] - t[:, 0]) ** 2).mean() + 1.0 * ((y[:, 1:4] - t[:, 1:4]) ** 2).mean() + 0.5 * (
        ((y[:, 4] - t[:, 4]) ** 2).mean() + ((y[:, 5] - t[:, 5]) ** 2).mean())


def read_init(folder, meta, params):
    """neuvolex's initial parameters as {name: float32 numpy array}, checked against `params`
    ({name: shape} of the model's parameters): every parameter once with its shape, the
    tensors tiling init.f32 exactly. Raises ValueError (with the reason) otherwise; needs
    numpy only."""
    spec = meta.get("init") or {}
    if "file" not in spec:
        raise ValueError(f"no initial parameters exported ({spec.get('skipped', 'meta.json has no init')})")
    flat = np.fromfile(os.path.join(folder, spec["file"]), dtype="<f4")
    if flat.size != spec["floats"]:
        raise ValueError(f"{spec['file']} holds {flat.size} floats, meta.json says {spec['floats']}")
    names = [t["name"] for t in spec["tensors"]]
    if sorted(names) != sorted(params):
        missing = sorted(set(params) - set(names))
        extra = sorted(set(names) - set(params))
        raise ValueError(f"tensors differ from the model's parameters (missing {missing}, unknown {extra})")
    out, spans = {}, []
    for t in spec["tensors"]:
        shape = tuple(int(d) for d in t["shape"])
        if shape != tuple(params[t["name"]]):
            raise ValueError(f"{t['name']}: neuvolex's shape {shape}, the model's {tuple(params[t['name']])}")
        n = int(np.prod(shape))
        o = int(t["offset"])
        spans.append((o, n))
        out[t["name"]] = flat[o:o + n].reshape(shape)
    end = 0
    for o, n in sorted(spans):
        if o != end:
            raise ValueError(f"the tensors leave a gap or overlap at element {end}")
        end = o + n
    if end != flat.size:
        raise ValueError(f"the tensors cover {end} of {flat.size} floats")
    if not all(np.isfinite(v).all() for v in out.values()):
        raise ValueError("non-finite initial parameters")
    return out


class Data:
    """The Rust bench's export, on the device."""

    def __init__(self, folder, dev):
        m = json.load(open(os.path.join(folder, "meta.json")))
        self.meta = m
        X, Y, Z = m["dims"]
        r = m["radius"]
        self.dims = (X, Y, Z)
        px, py, pz = X + 2 * r, Y + 2 * r, Z + 2 * r
        vol = np.fromfile(os.path.join(folder, "volume.f32"), dtype=np.float32)
        assert vol.size == px * py * pz, "volume.f32 does not match meta.json"
        tg = np.fromfile(os.path.join(folder, "targets.f32"), dtype=np.float32).reshape(-1, 6)
        assert tg.shape[0] == X * Y * Z, "targets.f32 does not match meta.json"
        order = np.fromfile(os.path.join(folder, "order.u32"), dtype=np.uint32).astype(np.int64)
        self.batch, self.steps = m["batch"], m["steps"]
        assert order.size >= self.batch * self.steps, "order.u32 is shorter than steps x batch"
        self.vol = torch.from_numpy(vol).to(dev)
        self.targets = torch.from_numpy(tg).to(dev)
        self.order = torch.from_numpy(order[: self.batch * self.steps]).to(dev)
        self.voxels = X * Y * Z
        p = 2 * r + 1
        off = [(dz * py + dy) * px + dx for dz in range(p) for dy in range(p) for dx in range(p)]
        self.off = torch.tensor(off, dtype=torch.long, device=dev)
        self.stride = (px, py)
        self.half = torch.tensor([0.5 / X, 0.5 / Y, 0.5 / Z], dtype=torch.float32, device=dev)
        self.dims_f = torch.tensor([X, Y, Z], dtype=torch.float32, device=dev)
        # Every voxel, in chunks of one fixed size (the last padded with voxel 0).
        eb = m["extract_batch"]
        n = -(-self.voxels // eb) * eb
        allv = torch.zeros(n, dtype=torch.long)
        allv[: self.voxels] = torch.arange(self.voxels)
        self.all = allv.to(dev)
        self.extract_batch = eb
        if dev.type == "cuda":
            # Resident inputs at fixed addresses: CUDA graphs read them in place instead of
            # copying them into the graph's input buffers at every replay.
            for t in (self.vol, self.targets, self.off, self.half, self.dims_f):
                try:
                    torch._dynamo.mark_static_address(t)
                except Exception as e:  # older torch: copies, still correct
                    note(f"mark_static_address unavailable ({e})")
                    break
        # The extraction output, shared by the variants (one runs at a time).
        self.out_h = torch.empty(n, 64, device=dev)
        self.out_y = torch.empty(n, 6, device=dev)


def make_gather(d):
    """Positions, patches and targets of linear voxel indices (inside the timed step)."""
    X, Y, _ = d.dims
    px, py = d.stride
    vol, targets, off, half, dims_f = d.vol, d.targets, d.off, d.half, d.dims_f

    def gather(idx):
        x = idx % X
        y = (idx // X) % Y
        z = idx // (X * Y)
        coords = torch.stack([x, y, z], 1).to(torch.float32) / dims_f + half
        base = (z * py + y) * px + x
        patches = vol[base[:, None] + off[None, :]]
        return coords, patches, targets[idx]

    return gather


class Variant:
    def __init__(self, name, d, init, dev):
        self.name = name
        self.dev = dev
        cuda = dev.type == "cuda"
        sparse = name.startswith("sparse")
        compiled = name.startswith(("compile", "ro+", "ma+")) or name == "sparse+compile"
        mode = {"ro": "reduce-overhead", "ma": "max-autotune"}.get(name.split("+")[0], "default")
        if mode != "default" and not cuda:
            raise RuntimeError(f"{name} needs CUDA (CUDA graphs)")
        self.mode = mode
        self.cudagraphs = mode != "default"
        model = Inr(d.meta["finest"], sparse=sparse).to(dev)
        model.load_state_dict(init)
        self.model = model
        self.init = [p.detach().clone() for p in model.parameters()]
        table = model.grid.table.weight
        rest = [p for p in model.parameters() if p is not table]
        lr, lr_t = d.meta["lr"], d.meta["lr_table"]
        fused = name in ("fused", "compile+fused", "ro+fused") or name == "sparse+compile"
        self.notes = []
        if sparse:
            self.opts = [torch.optim.SparseAdam([table], lr=lr_t)]
            self.opts.append(self._adam(rest, lr, fused))
        else:
            groups = [{"params": [table], "lr": lr_t}, {"params": rest, "lr": lr}]
            self.opts = [self._adam(groups, lr, fused)]
        cstep = name.endswith("+cstep")
        if cstep:
            step_all = self._step_plain
            self._step_opt = torch.compile(step_all, mode=None if mode == "default" else mode,
                                           fullgraph=False)
        else:
            self._step_opt = self._step_plain
        gather = make_gather(d)
        self.gather = gather
        kw = {} if mode == "default" else {"mode": mode}
        if name == "sparse+compile":
            grid = model.grid

            def index_fn(idx):
                coords, patches, t = gather(idx)
                i, w = grid.indices(coords)
                return i, w, patches, t

            def rest_loss(pos, patches, t):
                return loss_fn(model.rest(pos, patches)[0], t)

            ci = torch.compile(index_fn, **kw)
            cr = torch.compile(rest_loss, **kw)

            def train_loss(idx):
                i, w, patches, t = ci(idx)
                return cr(grid.blend(w, grid.table(i)), patches, t)

            self.train_loss = train_loss
        else:
            def train_loss(idx):
                coords, patches, t = gather(idx)
                return loss_fn(model(coords, patches)[0], t)

            self.train_loss = torch.compile(train_loss, **kw) if compiled else train_loss

        def extract_fn(idx):
            coords, patches, _ = gather(idx)
            return model(coords, patches)

        self.extract_fn = torch.compile(extract_fn, **kw) if compiled else extract_fn
        self.out_h, self.out_y = d.out_h, d.out_y

    def _adam(self, params, lr, fused):
        if fused:
            try:
                return torch.optim.Adam(params, lr=lr, fused=True)
            except (RuntimeError, ValueError, TypeError) as e:
                msg = f"Adam(fused=True) unavailable on {self.dev.type} ({e}); default Adam used"
                note(f"{self.name}: {msg}")
                self.notes.append(msg)
        return torch.optim.Adam(params, lr=lr)

    def _step_plain(self):
        for o in self.opts:
            o.step()

    def reset(self):
        """The same initial parameters and a zero optimiser state (in place: compiled graphs
        and CUDA graphs keep their inputs)."""
        with torch.no_grad():
            for p, p0 in zip(self.model.parameters(), self.init):
                p.copy_(p0)
                p.grad = None
            for o in self.opts:
                for st in o.state.values():
                    for k, v in list(st.items()):
                        if torch.is_tensor(v):
                            v.zero_()
                        else:
                            st[k] = type(v)(0)

    def step(self, idx):
        if self.cudagraphs:
            torch.compiler.cudagraph_mark_step_begin()
        for o in self.opts:
            o.zero_grad(set_to_none=True)
        loss = self.train_loss(idx)
        loss.backward()
        self._step_opt()
        # A CUDA graph's output is overwritten by its next replay: keep a copy of the loss.
        return loss.detach().clone() if self.cudagraphs else loss.detach()

    def extract(self, d):
        eb = d.extract_batch
        with torch.no_grad():
            for i in range(0, d.all.numel(), eb):
                if self.cudagraphs:
                    torch.compiler.cudagraph_mark_step_begin()
                y, h = self.extract_fn(d.all[i:i + eb])
                self.out_h[i:i + eb].copy_(h)
                self.out_y[i:i + eb].copy_(y)

    def warm(self, d):
        """Compiles and runs the step (3 times; 5 with CUDA graphs: warm-up, capture, replay)
        and the no_grad extraction (2 chunks; 3 with CUDA graphs), then resets."""
        t0 = time.perf_counter()
        for s in range(5 if self.cudagraphs else 3):
            self.step(d.order[s * d.batch:(s + 1) * d.batch])
        eb = d.extract_batch
        with torch.no_grad():
            for i in range(3 if self.cudagraphs else 2):
                if self.cudagraphs:
                    torch.compiler.cudagraph_mark_step_begin()
                y, h = self.extract_fn(d.all[i * eb:(i + 1) * eb])
                self.out_h[i * eb:(i + 1) * eb].copy_(h)
        sync(self.dev)
        self.reset()
        return time.perf_counter() - t0


def sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize()


def run_round(v, d):
    v.reset()
    sync(v.dev)
    t0 = time.perf_counter()
    last = None
    for s in range(d.steps):
        last = v.step(d.order[s * d.batch:(s + 1) * d.batch])
    sync(v.dev)
    train_s = time.perf_counter() - t0
    last_loss = float(last.item())
    sync(v.dev)
    t0 = time.perf_counter()
    v.extract(d)
    sync(v.dev)
    extract_s = time.perf_counter() - t0
    # Untimed: loss and PSNR over every voxel, from the extraction pass's heads.
    y = v.out_y[: d.voxels].double()
    t = d.targets.double()
    e2 = (y - t) ** 2
    mse_int = e2[:, 0].mean().item()
    vol_loss = (e2[:, 0].mean() + e2[:, 1:4].mean() + 0.5 * (e2[:, 4].mean() + e2[:, 5].mean())).item()
    samples = d.steps * d.batch
    return {"variant": v.name, "torch": torch.__version__, "device": v.dev.type, "init": d.init_from,
            "threads": torch.get_num_threads(), "steps": d.steps, "batch": d.batch,
            "samples": samples, "train_s": train_s, "train_samples_per_s": samples / train_s,
            "last_batch_loss": last_loss, "extract_voxels": d.voxels, "extract_s": extract_s,
            "extract_voxels_per_s": d.voxels / extract_s, "volume_loss": vol_loss,
            "volume_psnr": 10 * math.log10(1 / max(mse_int, 1e-12)), "notes": v.notes}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default="eager,fused,sparse,compile+fused,compile+cstep,sparse+compile")
    ap.add_argument("--serve", action="store_true")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    try:
        torch.set_num_interop_threads(a.threads)
    except RuntimeError:
        pass
    dev = torch.device(a.device)
    if dev.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = False  # f32 on both sides
    d = Data(a.data, dev)
    torch.manual_seed(0)
    ref = Inr(d.meta["finest"])
    res = ref.grid.resl.tolist()
    if "levels" in d.meta and res != d.meta["levels"]:
        sys.exit(f"hash-grid resolutions {res} differ from neuvolex's {d.meta['levels']}")
    init = ref.state_dict()
    # neuvolex's initial parameters where exported and matching; PyTorch's seed 0 otherwise.
    try:
        params = {n: tuple(p.shape) for n, p in ref.named_parameters()}
        for n, v in read_init(a.data, d.meta, params).items():
            init[n] = torch.from_numpy(v.copy())
        init_from = f"neuvolex (init.f32, {len(params)} tensors)"
    except (OSError, ValueError, KeyError, TypeError) as e:
        init_from = f"PyTorch seed 0 (neuvolex's initial parameters not loaded: {e})"
    note(f"initial parameters: {init_from}")
    init_check = None
    chk = (d.meta.get("init") or {}).get("check")
    if chk and init_from.startswith("neuvolex"):
        # The same function, not only the same numbers: this model's heads on the first
        # samples against neuvolex's, with the loaded parameters.
        try:
            ref.load_state_dict(init)
            ref.to(dev)
            with torch.no_grad():
                idx = d.order[torch.tensor(chk["order_index"], dtype=torch.long, device=dev)]
                coords, patches, _ = make_gather(d)(idx)
                y = ref(coords, patches)[0].double().cpu()
            want = torch.tensor(chk["outputs"], dtype=torch.float64)
            diff = (y - want).abs().max().item()
            init_check = {"samples": len(want), "max_abs_diff": diff,
                          "max_abs": want.abs().max().item()}
            note(f"initial parameters: heads on {len(want)} samples within {diff:.2e} of neuvolex's")
        except Exception as e:  # reported, never fatal
            init_check = {"error": f"{type(e).__name__}: {e}"}
    d.init_check = init_check
    d.init_from = init_from
    variants, ready = [], {"ready": True, "torch": torch.__version__, "device": a.device,
                           "threads": torch.get_num_threads(), "variants": {}, "failed": {},
                           "init": init_from, "init_check": init_check}
    for name in [v for v in a.variants.split(",") if v]:
        try:
            v = Variant(name, d, init, dev)
            secs = v.warm(d)
            variants.append(v)
            ready["variants"][name] = {"setup_s": secs, "notes": v.notes}
            note(f"{name}: compiled and warmed up in {secs:.1f} s")
        except Exception as e:  # a variant this torch cannot build: reported, left out
            msg = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
            ready["failed"][name] = msg
            note(f"{name}: FAILED ({msg}); left out")
    print(json.dumps(ready), flush=True)
    by = {v.name: v for v in variants}
    if a.serve:
        for line in sys.stdin:
            if not line.strip():
                continue
            if line.strip() == "quit":
                break
            cmd = json.loads(line)
            if cmd.get("cmd") == "quit":
                break
            v = by.get(cmd.get("variant"))
            if v is None:
                print(json.dumps({"variant": cmd.get("variant"), "error": "unknown or failed variant"}), flush=True)
                continue
            try:
                print(json.dumps(run_round(v, d)), flush=True)
            except Exception as e:
                print(json.dumps({"variant": v.name, "error": f"{type(e).__name__}: {e}"}), flush=True)
    else:
        for r in range(a.rounds):
            for v in variants:
                out = run_round(v, d)
                out["round"] = r
                print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
