"""scikit-learn's KMeans on the rows written by `benches/kmeans.rs`.

Same settings: k clusters, k-means++ (scikit-learn's greedy variant), one initialisation,
Lloyd, max_iter 100, tol 1e-4. Prints one JSON line with the fit seconds and the inertia.
Usage: python3 kmeans_sklearn.py ROWS.f32 DIM K
"""
import json
import sys
import time

import numpy as np
from sklearn.cluster import KMeans

path, dim, k = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
x = np.fromfile(path, dtype=np.float32).reshape(-1, dim)
km = KMeans(n_clusters=k, n_init=1, max_iter=100, tol=1e-4, random_state=0, algorithm="lloyd")
t = time.perf_counter()
km.fit(x)
fit = time.perf_counter() - t
print(json.dumps({"sklearn": __import__("sklearn").__version__, "fit_s": fit,
                  "inertia": float(km.inertia_), "iterations": int(km.n_iter_)}))
