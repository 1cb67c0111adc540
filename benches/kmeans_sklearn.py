"""scikit-learn's KMeans as a persistent server for `benches/kmeans.rs`, so its fits interleave
with neuvolex's and a load change on the machine hits both sides alike.

Usage: python3 kmeans_sklearn.py THREADS. Limits every thread pool (OpenMP, BLAS) to THREADS
with threadpoolctl for the process's life (the bench also sets OMP_NUM_THREADS) and prints one
JSON line: {"ready": true, "sklearn", "numpy", "openmp_threads" (what KMeans will use),
"pools": threadpoolctl's pools and their threads}, or {"error": ...} where an import fails.
Then it answers one JSON line per command on stdin:

- `load ROWS.f32 INIT.f32 DIM K MAX_ITER`: reads the rows (little-endian float32, row-major)
  into a float32 C-contiguous array and the k x dim initial centroids, outside any timing;
  replies {"rows", "dim"};
- `fit lloyd` / `fit elkan`: KMeans(n_clusters=K, init=INIT, n_init=1, max_iter=MAX_ITER,
  tol=0, algorithm=...) with the default copy_x=True (fit copies x and centres it on its
  mean); times `km.fit(x)` only and replies {"fit_s", "inertia" (of the fitted centres and
  labels, recomputed after the timing with float32 distances summed in float64, as neuvolex
  sums), "inertia_sklearn" (`inertia_`, scikit-learn's float32 sum), "iterations"};
- `quit`.

With tol=0 scikit-learn stops at max_iter or on strict convergence (labels unchanged between
two iterations); its non-zero tol would be scaled by the mean per-feature variance of all rows.
"""
import json
import sys
import time


def reply(obj):
    print(json.dumps(obj), flush=True)


def main():
    threads = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    try:
        import numpy as np
        import sklearn
        from sklearn.cluster import KMeans
        from sklearn.utils._openmp_helpers import _openmp_effective_n_threads
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError as e:
        reply({"error": f"{type(e).__name__}: {e}"})
        return
    limits = threadpool_limits(limits=threads)  # noqa: F841 (held for the process's life)
    reply({
        "ready": True,
        "sklearn": sklearn.__version__,
        "numpy": np.__version__,
        "openmp_threads": _openmp_effective_n_threads(),
        "pools": [f"{p['internal_api']}:{p['num_threads']}" for p in threadpool_info()],
    })
    x = init = None
    k = max_iter = 0
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        try:
            if cmd[0] == "quit":
                break
            if cmd[0] == "load":
                path, init_path, dim, k, max_iter = cmd[1], cmd[2], *map(int, cmd[3:6])
                x = None
                x = np.fromfile(path, dtype=np.float32).reshape(-1, dim)
                init = np.fromfile(init_path, dtype=np.float32).reshape(k, dim)
                assert x.dtype == np.float32 and x.flags.c_contiguous
                reply({"rows": x.shape[0], "dim": x.shape[1]})
            elif cmd[0] == "fit":
                km = KMeans(n_clusters=k, init=init, n_init=1, max_iter=max_iter, tol=0.0,
                            algorithm=cmd[1])
                t = time.perf_counter()
                km.fit(x)
                fit = time.perf_counter() - t
                # Outside the timing: the inertia of the fitted centres and labels with each
                # row's squared distance in float32 and the sum in float64, as neuvolex sums
                # (scikit-learn's own `inertia_` is a float32 sum over all rows).
                c = km.cluster_centers_.astype(np.float32)
                inertia = 0.0
                for s in range(0, x.shape[0], 1 << 20):
                    d = x[s:s + (1 << 20)] - c[km.labels_[s:s + (1 << 20)]]
                    inertia += float(np.einsum("ij,ij->i", d, d).sum(dtype=np.float64))
                reply({"fit_s": fit, "inertia": inertia, "inertia_sklearn": float(km.inertia_),
                       "iterations": int(km.n_iter_)})
            else:
                reply({"error": f"unknown command {cmd[0]}"})
        except Exception as e:  # reported to the bench, which prints it
            reply({"error": f"{type(e).__name__}: {e}"})


if __name__ == "__main__":
    main()
