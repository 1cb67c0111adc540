"""scikit-learn's RandomForestClassifier on the inputs written by `benches/forest.rs`.

Same settings as neuvolex's forest: n_estimators=T, min_samples_split=8, max_features='sqrt',
bootstrap=False, Gini. Prints one JSON line: fit and predict seconds, and the mean F1 over the
foreground classes (background 0 excluded).
Prediction runs REPEAT times (default 1); predict_s lists every time.
Usage: python3 forest_sklearn.py DIR TREES THREADS [REPEAT]
"""
import json
import sys
import time

import numpy as np
from sklearn.ensemble import RandomForestClassifier
from sklearn.metrics import f1_score

d, trees, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
repeat = int(sys.argv[4]) if len(sys.argv) > 4 else 1
meta = json.load(open(f"{d}/meta.json"))
xtr = np.fromfile(f"{d}/xtr.f32", dtype=np.float32).reshape(-1, meta["d"])
ytr = np.fromfile(f"{d}/ytr.u16", dtype=np.uint16)
xte = np.fromfile(f"{d}/xte.f32", dtype=np.float32).reshape(-1, meta["d"])
yte = np.fromfile(f"{d}/yte.u16", dtype=np.uint16)
rf = RandomForestClassifier(n_estimators=trees, min_samples_split=8, max_features="sqrt",
                            bootstrap=False, n_jobs=threads, random_state=0)
t = time.perf_counter()
rf.fit(xtr, ytr)
fit = time.perf_counter() - t
predict = []
for _ in range(repeat):
    t = time.perf_counter()
    proba = rf.predict_proba(xte)
    pred = rf.classes_[proba.argmax(1)]
    predict.append(time.perf_counter() - t)
fg = [c for c in range(1, meta["classes"]) if (yte == c).any()]
f1 = f1_score(yte, pred, labels=fg, average=None)
print(json.dumps({"sklearn": __import__("sklearn").__version__, "fit_s": fit, "predict_s": predict,
                  "f1_mean": float(np.mean(f1)), "f1": [float(v) for v in f1]}))
