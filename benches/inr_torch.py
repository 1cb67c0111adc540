"""The NeuVolEx INR in plain PyTorch: the reference a user would pick instead of neuvolex.

Same architecture and sizes as neuvolex-features (16 levels x 2 features, 2^19 table, base 16,
finest = the volume's largest dimension, dense indexing where the level fits the table, the
spatial hash otherwise; structural encoder 125-32-32 -> FiLM; 4x64 MLP with a residual
projection into the third layer; heads for intensity, gradient, mean, std; loss weights
1, 1, 0.5, 0.5), trained with torch.optim.Adam on the CPU or, with --device cuda, on an NVIDIA GPU (timed after
torch.cuda.synchronize, so queued kernels count).

Prints one JSON line: training samples/s and extraction (forward, no grad) voxels/s.
Usage: python3 inr_torch.py [--device cpu|cuda] [--threads 2] [--batch 16384] [--finest 161]
       [--seconds 20] [--sparse] [--compile [--compile-mode reduce-overhead]] [--fused-adam]
"""
import argparse
import json
import math
import time

import torch
import torch.nn as nn

P1, P2 = 2654435761, 805459861


class HashGrid(nn.Module):
    """All levels and corners in one gather from a flat [L*T, F] table (vectorised, as a
    PyTorch user would write it). With sparse=True the table is an nn.Embedding with sparse
    gradients, trained by SparseAdam (touched rows only, like neuvolex's lazy Adam)."""

    def __init__(self, levels=16, feats=2, log2t=19, base=16, finest=161, sparse=False):
        super().__init__()
        self.t = 1 << log2t
        self.l = levels
        b = math.exp((math.log(max(finest, base)) - math.log(base)) / (levels - 1))
        res = [int(math.floor(base * b ** l + 1e-9)) for l in range(levels)]
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32))
        self.register_buffer("resl", torch.tensor(res, dtype=torch.long))
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= self.t for r in res]))
        self.register_buffer("base", torch.arange(levels, dtype=torch.long) * self.t)
        self.register_buffer("off", torch.tensor([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)]))
        self.table = nn.Embedding(levels * self.t, feats, sparse=sparse)
        nn.init.uniform_(self.table.weight, -1e-4, 1e-4)

    def forward(self, x):
        p = x[:, None, :] * self.res[None, :, None]                       # [N, L, 3]
        c = torch.minimum(torch.floor(p), (self.res - 1)[None, :, None])
        f = p - c
        v = c.long()[:, :, None, :] + self.off[None, None]                # [N, L, 8, 3]
        r = (self.resl + 1)[None, :, None]
        dense_idx = v[..., 0] + v[..., 1] * r + v[..., 2] * r * r
        hash_idx = (v[..., 0] ^ (v[..., 1] * P1) ^ (v[..., 2] * P2)) & (self.t - 1)
        idx = torch.where(self.dense[None, :, None], dense_idx, hash_idx) + self.base[None, :, None]
        w = torch.where(self.off.bool()[None, None], f[:, :, None, :], 1 - f[:, :, None, :]).prod(-1)  # [N, L, 8]
        feats = self.table(idx)                                            # [N, L, 8, F]
        return (w[..., None] * feats).sum(2).flatten(1)


class Inr(nn.Module):
    def __init__(self, finest, sparse=False):
        super().__init__()
        self.grid = HashGrid(finest=finest, sparse=sparse)
        e = 32
        self.struct = nn.Sequential(nn.Linear(125, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU())
        self.film = nn.Linear(32, 2 * e)
        self.m = nn.ModuleList([nn.Linear(e, 64)] + [nn.Linear(64, 64) for _ in range(3)])
        self.proj = nn.Linear(e, 64, bias=False)
        self.head = nn.Linear(64, 6)

    def forward(self, x, patch):
        pos = self.grid(x)
        gb = self.film(self.struct(patch))
        inp = pos * (gb[:, :32] + 1) + gb[:, 32:]
        h = inp
        for k, layer in enumerate(self.m):
            z = layer(h)
            if k == 2:
                z = z + self.proj(inp)
            h = torch.relu(z)
        return self.head(h), h


def loss_fn(y, t):
    return ((y[:, 0] - t[:, 0]) ** 2).mean() + 1.0 * ((y[:, 1:4] - t[:, 1:4]) ** 2).mean() + 0.5 * (
        ((y[:, 4] - t[:, 4]) ** 2).mean() + ((y[:, 5] - t[:, 5]) ** 2).mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=16384)
    ap.add_argument("--finest", type=int, default=161)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--sparse", action="store_true", help="sparse table gradients + SparseAdam")
    ap.add_argument("--compile", action="store_true", help="torch.compile the model")
    ap.add_argument("--compile-mode", default="default",
                    help="torch.compile mode: default, reduce-overhead (CUDA graphs), max-autotune")
    ap.add_argument("--fused-adam", action="store_true", help="Adam(fused=True) (CUDA), dense gradients")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    dev = torch.device(a.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    model = Inr(a.finest, a.sparse).to(dev)
    rest = [p for n, p in model.named_parameters() if n != "grid.table.weight"]
    fwd = torch.compile(model, mode=a.compile_mode) if a.compile else model
    if a.sparse:
        opts = [torch.optim.SparseAdam([model.grid.table.weight], lr=1e-2), torch.optim.Adam(rest, lr=1e-3)]
    else:
        extra = {"fused": True} if a.fused_adam else {}
        opts = [torch.optim.Adam([{"params": [model.grid.table.weight], "lr": 1e-2}, {"params": rest, "lr": 1e-3}], **extra)]

    class Multi:
        def zero_grad(self):
            for o in opts:
                o.zero_grad()

        def step(self):
            for o in opts:
                o.step()

    opt = Multi()
    n = a.batch
    gen = lambda: (torch.rand(n, 3, device=dev), torch.rand(n, 125, device=dev), torch.rand(n, 6, device=dev))
    x, p, t = gen()
    # Warm-up outside the timed windows: compilation, CUDA-graph capture (a few steps), and the
    # no-grad graph the extraction timing uses.
    for _ in range(5):
        opt.zero_grad()
        loss_fn(fwd(x, p)[0], t).backward()
        opt.step()
    with torch.no_grad():
        for _ in range(3):
            fwd(x, p)
    sync()
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < a.seconds:
        x, p, t = gen()
        opt.zero_grad()
        loss_fn(fwd(x, p)[0], t).backward()
        opt.step()
        steps += 1
    sync()
    train = steps * n / (time.perf_counter() - t0)
    with torch.no_grad():
        reps, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < a.seconds / 2:
            fwd(x, p)
            reps += 1
        sync()
        extract = reps * n / (time.perf_counter() - t0)
    print(json.dumps({"torch": torch.__version__, "device": a.device, "threads": a.threads, "batch": n, "sparse": a.sparse, "compile": a.compile,
                      "compile_mode": a.compile_mode if a.compile else None, "fused_adam": a.fused_adam,
                      "train_samples_per_s": train, "extract_voxels_per_s": extract}))


if __name__ == "__main__":
    main()
