"""scikit-learn's RandomForestClassifier on the inputs written by `benches/forest.rs`.

Same settings as neuvolex's forest: n_estimators=T, min_samples_split=8, max_features='sqrt',
bootstrap=False, Gini, class_weight from meta.json (the classifier's "balanced"), n_jobs=THREADS. Loads the arrays once (outside every timed region), prints
`{"ready": version}`, then serves commands on stdin, one per line, so the bench can interleave
its rounds with neuvolex's:

- `fit`: fits a new forest (random_state = the round) and prints `{"fit_s"}`: the timed region
  is `fit` alone (scikit-learn builds its tree arrays inside it);
- `predict`: predicts the test rows with the last forest and prints `{"predict_s", "f1_mean",
  "f1"}`: the timed region is `predict_proba` and the argmax; F1 over the foreground classes
  (background 0 excluded) is computed after the timer;
- `quit`.

Usage: python3 forest_sklearn.py DIR TREES THREADS
"""
import json
import sys
import time

import numpy as np
import sklearn
from sklearn.ensemble import RandomForestClassifier
from sklearn.metrics import f1_score


def main():
    d, trees, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    meta = json.load(open(f"{d}/meta.json"))
    xtr = np.fromfile(f"{d}/xtr.f32", dtype=np.float32).reshape(-1, meta["d"])
    ytr = np.fromfile(f"{d}/ytr.u16", dtype=np.uint16)
    xte = np.fromfile(f"{d}/xte.f32", dtype=np.float32).reshape(-1, meta["d"])
    yte = np.fromfile(f"{d}/yte.u16", dtype=np.uint16)
    fg = [c for c in range(1, meta["classes"]) if (yte == c).any()]
    rf, rounds = None, 0
    print(json.dumps({"ready": sklearn.__version__}), flush=True)
    for line in sys.stdin:
        cmd = line.strip()
        if cmd == "quit":
            break
        if cmd == "fit":
            rf = RandomForestClassifier(n_estimators=trees, min_samples_split=8,
                                        max_features="sqrt", bootstrap=False, n_jobs=threads,
                                        class_weight=meta.get("class_weight"),
                                        random_state=rounds)
            rounds += 1
            t = time.perf_counter()
            rf.fit(xtr, ytr)
            print(json.dumps({"fit_s": time.perf_counter() - t}), flush=True)
        elif cmd == "predict" and rf is not None:
            t = time.perf_counter()
            proba = rf.predict_proba(xte)
            pred = rf.classes_[proba.argmax(1)]
            s = time.perf_counter() - t
            f1 = f1_score(yte, pred, labels=fg, average=None)
            print(json.dumps({"predict_s": s, "f1_mean": float(np.mean(f1)),
                              "f1": [float(v) for v in f1]}), flush=True)
        else:
            print(json.dumps({"error": f"unknown or early command {cmd!r}"}), flush=True)


if __name__ == "__main__":
    main()
