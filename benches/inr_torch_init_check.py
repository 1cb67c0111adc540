"""Checks the initial parameters the inr_gpu/inr benches export for PyTorch, without torch
(numpy only): inr_torch.py's `read_init` loads init.f32 by meta.json's tensor list (every
parameter once, with its shape, tiling the file) and refuses a wrong shape or a missing tensor;
then a numpy port of inr_torch.py's forward pass (hash grid, structural encoder, FiLM, residual
MLP, heads) with those parameters reproduces neuvolex's head outputs on the first samples
(meta.json's init.check), so the two sides start from the same function, not only the same
numbers. Exits non-zero on any failure.

    NEUVOLEX_TORCH_DATA=/tmp/export target/release/deps/inr_gpu-* --only torch --paths fused \
        --torch-steps 2 --rounds 0     # the export is written first; the rest may be stopped
    python3 benches/inr_torch_init_check.py /tmp/export
"""
import os
import importlib.util, json, sys, types
torch = types.ModuleType("torch"); nn = types.ModuleType("torch.nn")
nn.Module = object; torch.nn = nn
sys.modules["torch"] = torch; sys.modules["torch.nn"] = nn
spec = importlib.util.spec_from_file_location(
    "inr_torch", os.path.join(os.path.dirname(os.path.abspath(__file__)), "inr_torch.py"))
m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)
d = sys.argv[1]
meta = json.load(open(d + "/meta.json"))
L, T, F = 16, 1 << 19, 2
params = {"grid.table.weight": (L * T, F),
          "rest.struct.0.weight": (32, 125), "rest.struct.0.bias": (32,),
          "rest.struct.2.weight": (32, 32), "rest.struct.2.bias": (32,),
          "rest.film.weight": (64, 32), "rest.film.bias": (64,),
          "rest.proj.weight": (64, 32), "rest.head.weight": (6, 64), "rest.head.bias": (6,)}
for k in range(4):
    params[f"rest.m.{k}.weight"] = (64, 32 if k == 0 else 64)
    params[f"rest.m.{k}.bias"] = (64,)
out = m.read_init(d, meta, params)
print(len(out), "tensors;", {k: v.shape for k, v in list(out.items())[:4]})
import numpy as np
t = out["grid.table.weight"]; print("table range", float(t.min()), float(t.max()))
w = out["rest.struct.0.weight"]; print("struct0 std", float(w.std()), "bias", out["rest.struct.0.bias"][:3])
# Failure cases: a wrong shape and a missing tensor must be refused.
bad = dict(params); bad["rest.head.weight"] = (7, 64)
try:
    m.read_init(d, meta, bad)
    sys.exit("FAIL: a wrong shape was accepted")
except ValueError as e:
    print("refused as expected:", e)
bad = dict(params); del bad["rest.proj.weight"]
try:
    m.read_init(d, meta, bad)
    sys.exit("FAIL: a missing tensor was accepted")
except ValueError as e:
    print("refused as expected:", e)

# A numpy port of inr_torch.py's forward (HashGrid.indices/blend, Rest.forward) with the
# loaded parameters, on the samples neuvolex reports its heads for.
chk = meta["init"]["check"]
X, Y, Z = meta["dims"]; r = meta["radius"]
px, py, pz = X + 2 * r, Y + 2 * r, Z + 2 * r
vol = np.fromfile(d + "/volume.f32", dtype="<f4")
order = np.fromfile(d + "/order.u32", dtype="<u4").astype(np.int64)
idx = order[chk["order_index"]]
x = idx % X; yy = (idx // X) % Y; z = idx // (X * Y)
coords = np.stack([x, yy, z], 1).astype(np.float32) / np.array([X, Y, Z], np.float32) + np.array([0.5 / X, 0.5 / Y, 0.5 / Z], np.float32)
p = 2 * r + 1
off = np.array([(dz * py + dy) * px + dx for dz in range(p) for dy in range(p) for dx in range(p)])
base = (z * py + yy) * px + x
patches = vol[base[:, None] + off[None, :]]
import math
finest = meta["finest"]; b = math.exp((math.log(max(finest, 16)) - math.log(16)) / 15)
res = np.array([int(math.floor(16 * b ** l + 1e-9)) for l in range(16)])
assert list(res) == meta["levels"]
P1, P2 = 2654435761, 805459861
cor = np.array([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)])
pp = np.clip(coords, 0, 1)[:, None, :] * res[None, :, None]
c = np.minimum(np.floor(pp), (res - 1)[None, :, None]); f = pp - c
v = c.astype(np.int64)[:, :, None, :] + cor[None, None]
rr = (res + 1)[None, :, None]
dense = ((res + 1) ** 3 <= T)[None, :, None]
di = v[..., 0] + v[..., 1] * rr + v[..., 2] * rr * rr
hi = (v[..., 0] ^ (v[..., 1] * P1) ^ (v[..., 2] * P2)) & (T - 1)
ix = np.where(dense, di, hi) + (np.arange(16) * T)[None, :, None]
w = np.where(cor.astype(bool)[None, None], f[:, :, None, :], 1 - f[:, :, None, :]).prod(-1)
pos = (w[..., None] * t[ix]).sum(2).reshape(len(idx), -1)
lin = lambda n, h: h @ out[n + ".weight"].T + (out[n + ".bias"] if n + ".bias" in out else 0)
relu = lambda a: np.maximum(a, 0)
s1 = relu(lin("rest.struct.2", relu(lin("rest.struct.0", patches))))
gb = lin("rest.film", s1)
inp = pos * (gb[:, :32] + 1) + gb[:, 32:]
h = inp
for k in range(4):
    zz = lin(f"rest.m.{k}", h)
    if k == 2:
        zz = zz + lin("rest.proj", inp)
    h = relu(zz)
yv = lin("rest.head", h)
want = np.array(chk["outputs"])
diff = float(np.abs(yv - want).max())
print(f"numpy port of the PyTorch forward against neuvolex's heads on {len(want)} samples: "
      f"largest difference {diff:.2e} (largest |output| {float(np.abs(want).max()):.3f})")
if not diff <= 1e-5 * max(1.0, float(np.abs(want).max())):
    sys.exit("FAIL: the two forward passes differ")
print("PASS")
