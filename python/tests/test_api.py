"""The `neuvolex` Python API against the built wheel: round trips, geometry, errors, the CLI's
labels bit for bit, progress, the GIL, Ctrl-C."""

import _thread
import os
import subprocess
import threading
import time

import nibabel as nib
import numpy as np
import pytest

import neuvolex
from conftest import need, spheres, strokes


def test_from_array_round_trips_every_type_and_layout():
    v, _ = spheres((20, 24, 28))
    for dt in (np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32, np.float32, np.float64):
        a = np.clip(v, -100, 120).astype(dt)
        for arr in (a, np.asfortranarray(a), a[:, ::-1, :]):
            s = neuvolex.from_array(arr)
            assert s.shape == arr.shape
            np.testing.assert_array_equal(s.read(), arr.astype(np.float32), err_msg=str(dt))


def test_geometry_is_kept_from_spacing_origin_and_affine(tmp_path):
    v, lab = spheres((20, 24, 28))
    s = neuvolex.from_array(v, spacing=(3.0, 2.0, 0.5), origin=(-7.0, 11.0, 40.0))
    assert s.spacing == (3.0, 2.0, 0.5)
    a = s.affine
    np.testing.assert_allclose(np.diag(a)[:3], [0.5, 2.0, 3.0])
    np.testing.assert_allclose(a[:3, 3], [40.0, 11.0, -7.0])
    # napari's axes: z, y, x in and out.
    n = s.napari_affine
    np.testing.assert_allclose(n @ [1, 2, 3, 1], [3 * 1 - 7, 2 * 2 + 11, 0.5 * 3 + 40, 1])
    # An oblique affine (nibabel's convention) survives the store and a NIfTI export.
    obl = np.array([[0, -0.8, 0.1, 12.5], [0.9, 0, 0, -30], [0, 0.05, 2.5, 7], [0, 0, 0, 1]])
    s = neuvolex.from_array(v, affine=obl)
    np.testing.assert_allclose(s.affine, obl)
    out = tmp_path / "labels.nii.gz"
    s.export(out, labels=lab)
    img = nib.load(out)
    np.testing.assert_allclose(img.affine, obl, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(img.dataobj).T, lab)
    with pytest.raises(ValueError, match="exists"):
        s.export(out, labels=lab)
    s.export(out, labels=lab, force=True)


def test_open_ingests_a_file_once_and_keeps_its_affine(tmp_path):
    v, _ = spheres((20, 24, 28))
    aff = np.array([[-1.5, 0, 0, 90], [0, 1.5, 0, -120], [0, 0, 2, -60], [0, 0, 0, 1]])
    p = tmp_path / "v.nii.gz"
    nib.save(nib.Nifti1Image(v.T.astype(np.int16), aff), p)
    s = neuvolex.open(p)
    np.testing.assert_allclose(s.affine, aff)
    np.testing.assert_array_equal(s.read(), v.astype(np.int16).astype(np.float32))
    stamp = os.path.getmtime(os.path.join(s.path, "zarr.json"))
    again = neuvolex.open(p)
    assert again.path == s.path
    assert os.path.getmtime(os.path.join(s.path, "zarr.json")) == stamp
    # An existing store opens as it is.
    assert neuvolex.open(s.path).shape == s.shape


def test_bad_input_is_a_clear_error(tmp_path):
    v, lab = spheres((20, 24, 28))
    s = neuvolex.from_array(v)
    scr = strokes(lab)
    cases = [
        (lambda: s.classify(scr[:5]), ValueError, r"scribbles: shape \[5, 24, 28\] differs"),
        (lambda: s.classify(scr.astype(np.float32)), ValueError, "scribbles: expected an integer"),
        (lambda: s.classify(scr.astype(np.int16) * -1), ValueError, r"scribbles: voxel \[z, y, x\]"),
        (lambda: s.classify(np.where(scr == 1, 1, 0)), ValueError, "one class only"),
        (lambda: s.classify(scr, trees=0), ValueError, "trees 0"),
        (lambda: s.classify(scr, tau=2), ValueError, "tau 2"),
        (lambda: s.classify(scr, features="nope"), ValueError, "features 'nope'"),
        (lambda: s.classify(scr, features="inr"), ValueError, "trained INR"),
        (lambda: s.classify(scr, class_weight="x"), ValueError, "class_weight 'x'"),
        (lambda: s.classify(scr, prior_mass=-1), ValueError, "prior_mass -1"),
        (lambda: s.classify("not an array"), ValueError, "scribbles: expected a numpy array"),
        (lambda: neuvolex.from_array(np.zeros((3, 3))), ValueError, "array: expected a 3-D array"),
        (lambda: neuvolex.from_array(np.zeros((3, 3, 3), np.complex64)), ValueError, "array: dtype complex64"),
        (lambda: neuvolex.from_array(np.zeros((3, 3, 3), np.int64)), ValueError, "64-bit integer"),
        (lambda: neuvolex.from_array(v, spacing=(1, 0, 1)), ValueError, "spacing"),
        (lambda: neuvolex.from_array(v, affine=np.eye(3)), ValueError, "affine"),
        (lambda: s.suggest_slice("w"), ValueError, "axis 'w'"),
        (lambda: s.train(preset="slow"), ValueError, "preset 'slow'"),
        (lambda: s.train(epochs=-1), ValueError, "epochs -1"),
        (lambda: s.viewpoints(k=0), ValueError, "k 0"),
        (lambda: neuvolex.render(s, size=0), ValueError, "render"),
        (lambda: neuvolex.render(s, probabilities=True), ValueError, "no classification yet"),
        (lambda: neuvolex.render(s, mode="x"), ValueError, "mode 'x'"),
        (lambda: s.export(tmp_path / "x.nii.gz"), ValueError, "no classification to export"),
        (lambda: neuvolex.open(tmp_path / "missing.nii.gz"), FileNotFoundError, "missing.nii.gz"),
    ]
    for call, kind, text in cases:
        with pytest.raises(kind, match=text):
            call()
    bad = tmp_path / "broken.nii.gz"
    bad.write_bytes(b"\x1f\x8b not really gzip")
    with pytest.raises(ValueError, match="broken.nii.gz"):
        neuvolex.open(bad)
    # Nothing written is lost: the store still classifies after every refusal.
    labels, _ = s.classify(scr)
    assert labels.shape == v.shape


def test_classify_finds_the_scribbled_objects_and_reports_probabilities():
    v, lab = spheres()
    s = neuvolex.from_array(v, spacing=(2.0, 1.0, 1.0))
    labels, proba = s.classify(strokes(lab), trees=50)
    assert s.classes == [1, 2, 255]
    assert s.last_report["trees"] == 50 and s.last_report["labels"] == [1, 2, 255]
    assert labels.dtype == np.uint8 and labels.shape == v.shape
    assert proba.shape == (3,) + v.shape and proba.dtype == np.float32
    np.testing.assert_allclose(proba.sum(axis=0), 1.0, atol=0.02)
    for c in (1, 2):
        inside = lab == c
        assert (labels[inside] == c).mean() > 0.8, c
    assert (labels[lab == 0] == 0).mean() > 0.98
    # The probabilities are the forest's, before the prior.
    assert (proba.argmax(axis=0)[lab == 1] == 0).mean() > 0.9
    z = s.suggest_slice("z")
    assert 0 <= z < v.shape[0]
    assert s.suggest_slice(0, visited=[z]) != z
    labels2, none = s.classify(strokes(lab), trees=50, probabilities=False)
    assert none is None
    np.testing.assert_array_equal(labels, labels2)


def _u8(p: np.ndarray) -> np.ndarray:
    """Probabilities as the stability rule compares them: round(clamp(p) * 255), halves up."""
    return np.floor(np.clip(p, 0, 1).astype(np.float32) * np.float32(255) + 0.5).astype(np.int32)


def test_corrections_stick_beyond_the_margin_of_new_scribbles():
    # Two spheres 63 voxels apart along x; a second call adds strokes on the far sphere only.
    v, lab = spheres(shape=(40, 48, 140), noise=30.0)
    first = strokes(lab)
    second = first.copy()
    zs = (16, 24)
    for z in zs:
        ys, xs = np.nonzero(lab[z] == 2)
        assert len(ys) > 0
        second[z, ys[::3], xs[::3]] = 2
        second[z, 44, 100:132:2] = 255
    trees = 8
    s = neuvolex.from_array(v)
    prev, _ = s.classify(first, trees=trees)
    assert s.last_report["voxels_held"] is None, "nothing to hold to yet"
    held, proba = s.classify(second, trees=trees)
    n_held = s.last_report["voxels_held"]
    # The same call on a fresh store: the same forest, every label as it alone finds it.
    fresh = neuvolex.from_array(v)
    alone, proba_alone = fresh.classify(second, trees=trees)
    np.testing.assert_array_equal(proba, proba_alone)
    # The rule, voxel by voxel: within 24 voxels (Chebyshev) of an added scribble the new
    # label stands; beyond, a changed voxel keeps its label unless the new one is more
    # probable by 0.25 (64 of 255).
    near = np.zeros(v.shape, bool)
    for z, y, x in zip(*np.nonzero((second != 0) & (first == 0))):
        near[max(z - 24, 0):z + 25, max(y - 24, 0):y + 25, max(x - 24, 0):x + 25] = True
    channel = {c: k for k, c in enumerate(fresh.classes)}
    p8 = _u8(proba_alone)

    def score(labels):
        out = np.zeros(labels.shape, np.int32)
        for value, k in [(c, channel[c]) for c in (1, 2)] + [(0, channel[255])]:
            out[labels == value] = p8[k][labels == value]
        return out

    keep = (~near) & (alone != prev) & (score(alone) < score(prev) + 64)
    expect = np.where(keep, prev, alone)
    np.testing.assert_array_equal(held, expect)
    assert n_held == int(keep.sum()) and n_held > 0, n_held
    # Near the new strokes nothing is held, and the far sphere follows the new scribbles.
    np.testing.assert_array_equal(held[near], alone[near])
    # Off, another setting, or erased scribbles: every label as the call alone finds it.
    s2 = neuvolex.from_array(v)
    s2.classify(first, trees=trees)
    off, _ = s2.classify(second, trees=trees, stable=None)
    np.testing.assert_array_equal(off, alone)
    s2.classify(first, trees=trees)
    s2.classify(second, trees=trees + 1)
    assert s2.last_report["voxels_held"] is None, "other settings"
    erased = second.copy()
    erased[first != 0] = 0
    s2.classify(erased, trees=trees + 1)
    assert s2.last_report["voxels_held"] is None, "erased scribbles"
    for bad in (1.5, -0.1):
        with pytest.raises(ValueError, match="stable"):
            s2.classify(second, stable=bad)


def _cli_classify(cli, tmp_path, volume, scribbles, trees, extra=()):
    store = tmp_path / "cli.zarr"
    out = tmp_path / "cli_labels.nii.gz"
    subprocess.run([cli, "--quiet", "ingest", volume, store], check=True, capture_output=True)
    subprocess.run(
        [cli, "--quiet", "classify", store, "--scribbles", scribbles, "--trees", str(trees), "--out", out, *extra],
        check=True,
        capture_output=True,
    )
    img = nib.load(out)
    return np.asarray(img.dataobj).T, img.affine


def test_classify_gives_the_cli_labels_bit_for_bit(cli, tmp_path):
    v, lab = spheres(noise=15.0)
    aff = np.diag([0.8, 0.8, 1.5, 1.0])
    vol = tmp_path / "v.nii.gz"
    scr = tmp_path / "s.nii.gz"
    nib.save(nib.Nifti1Image(v.T, aff), vol)
    nib.save(nib.Nifti1Image(strokes(lab).T, aff), scr)
    expect, affine = _cli_classify(cli, tmp_path, vol, scr, 60)
    s = neuvolex.open(vol)
    labels, _ = s.classify(np.asarray(nib.load(scr).dataobj).T, trees=60)
    np.testing.assert_array_equal(labels, expect)
    np.testing.assert_allclose(s.affine, affine, atol=1e-6)
    # And without the prior.
    (tmp_path / "no_prior").mkdir()
    expect, _ = _cli_classify(cli, tmp_path / "no_prior", vol, scr, 60, ["--no-prior"])
    labels, _ = s.classify(np.asarray(nib.load(scr).dataobj).T, trees=60, prior=False)
    np.testing.assert_array_equal(labels, expect)


def test_classify_gives_the_cli_labels_on_the_abdomen_ct(cli, data, tmp_path):
    ct = data / "abdomen_ct" / "ct.nii.gz"
    need(str(ct), ct.exists())
    scr = tmp_path / "s1.nii.gz"
    subprocess.run(
        [cli, "--quiet", "scribble-sim", data / "abdomen_ct" / "labels.nii.gz", "--level", "S1", "--out", scr],
        check=True,
        capture_output=True,
    )
    expect, affine = _cli_classify(cli, tmp_path, ct, scr, 100)
    s = neuvolex.open(ct)
    labels, proba = s.classify(np.asarray(nib.load(scr).dataobj).T, trees=100)
    assert labels.shape == (112, 101, 122)
    np.testing.assert_array_equal(labels, expect)
    np.testing.assert_allclose(s.affine, affine, atol=1e-5)
    assert len(np.unique(labels)) >= 4


def test_features_lazy_and_dense_agree():
    v, _ = spheres((40, 48, 56))
    s = neuvolex.from_array(v, brick=16)
    dense = s.features("filters+xyz")
    assert dense.shape == v.shape + (dense.shape[3],) and dense.dtype == np.float32
    lazy = s.features("filters+xyz", max_bytes=0)
    assert isinstance(lazy, neuvolex.FeatureArray) and lazy.shape == dense.shape
    np.testing.assert_array_equal(lazy[3:37:3, 20, 5:50], dense[3:37:3, 20, 5:50])
    np.testing.assert_array_equal(lazy[-1, -2:, :, 4], dense[-1, -2:, :, 4])
    np.testing.assert_array_equal(lazy.brick((1, 2, 3)), dense[16:32, 32:48, 48:56])
    np.testing.assert_array_equal(np.asarray(lazy), dense)


def test_render_viewpoints_and_labels():
    v, lab = spheres()
    s = neuvolex.from_array(v)
    img = neuvolex.render(s, size=(80, 60))
    assert img.shape == (60, 80, 4) and img.dtype == np.uint8
    assert img[..., 3].max() > 0
    labels, _ = s.classify(strokes(lab), trees=30)
    by_name = neuvolex.render(s, labels="classified", size=64)
    by_array = neuvolex.render(s, labels=labels, size=64)
    np.testing.assert_array_equal(by_name, by_array)
    assert np.abs(by_name.astype(int) - neuvolex.render(s, size=64).astype(int)).mean() > 1
    probs = neuvolex.render(s, probabilities=True, size=64, view=(90, 0))
    assert probs[..., 3].max() > 0
    views = s.viewpoints(k=4, views=200, max_views=3)
    assert 1 <= len(views) <= 3
    for w in views:
        assert -180 <= w["azimuth"] <= 360 and -90 <= w["elevation"] <= 90
        assert np.isclose(np.linalg.norm(w["direction"]), 1, atol=1e-4)


def test_progress_is_reported_and_the_gil_released():
    v, lab = spheres((64, 64, 64))
    s = neuvolex.from_array(v, brick=16)
    seen = []
    ticks = [0]
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            ticks[0] += 1
            time.sleep(0.001)

    t = threading.Thread(target=spin)
    t.start()
    try:
        before = ticks[0]
        s.classify(strokes(lab), trees=200, progress=lambda d, n, m: seen.append((d, n, m)))
        during = ticks[0] - before
    finally:
        stop.set()
        t.join()
    assert seen and seen[-1][0] == seen[-1][1] == 64, seen[-3:]
    assert during > 10, "another Python thread did not run during classify (the GIL was held)"


def test_a_raising_callback_stops_the_work():
    v, lab = spheres((64, 64, 64))
    s = neuvolex.from_array(v, brick=16)

    def boom(d, n, m):
        if d > 2:
            raise RuntimeError("stop here")

    with pytest.raises(RuntimeError, match="stop here"):
        s.classify(strokes(lab), trees=100, progress=boom)
    labels, _ = s.classify(strokes(lab), trees=20)
    assert labels.shape == v.shape


def test_ctrl_c_cancels_between_bricks_and_leaves_the_store_usable():
    v, lab = spheres((96, 96, 96))
    s = neuvolex.from_array(v, brick=16)
    # Ctrl+C once the first brick is done (a fixed timer raced the work on a fast machine: the
    # classification could end before it fired). 215 bricks of 400 trees remain then, far more
    # than the few milliseconds the interrupt takes to arrive.
    started = threading.Event()
    seen = []

    def interrupt():
        if started.wait(60):
            _thread.interrupt_main()

    t = threading.Thread(target=interrupt)
    t.start()

    def progress(d, n, m):
        seen.append((d, n))
        started.set()

    try:
        with pytest.raises(KeyboardInterrupt):
            s.classify(strokes(lab), trees=400, progress=progress)
    finally:
        started.set()
        t.join()
    # A whole run ends on (216, 216), its last brick.
    assert seen and seen[-1] != (216, 216), f"the work was not cut short: {seen[-3:]}"
    labels, _ = s.classify(strokes(lab), trees=20)
    assert (labels[lab == 1] == 1).mean() > 0.9


def test_train_reports_and_enables_inr_features():
    v, lab = spheres((32, 32, 32))
    s = neuvolex.from_array(v, brick=16)
    assert not s.trained
    calls = []
    r = s.train(seconds=2, progress=lambda d, n, m: calls.append(m))
    assert s.trained and r["samples"] > 0 and np.isfinite(r["psnr"])
    assert any("PSNR" in m for m in calls)
    labels, _ = s.classify(strokes(lab), features="inr", trees=20)
    assert (labels[lab == 1] == 1).mean() > 0.5


def test_the_slice_preview_is_that_slice_of_the_classification_without_prior():
    v, lab = spheres(noise=12.0)
    s = neuvolex.from_array(v, brick=16)
    scr = strokes(lab)
    full, _ = s.classify(scr, trees=30, prior=False, probabilities=False)
    for axis, index, cut in [("z", 20, lambda a: a[20]), (1, 17, lambda a: a[:, 17]), ("x", 55, lambda a: a[:, :, 55])]:
        plane = s.preview_slice(scr, axis=axis, index=index, trees=30)
        np.testing.assert_array_equal(plane, cut(full), err_msg=f"{axis} {index}")
    with pytest.raises(ValueError, match="index 40: the volume has 40 slices along z"):
        s.preview_slice(scr, "z", 40)
    with pytest.raises(ValueError, match="one class only"):
        s.preview_slice(np.where(scr == 1, 1, 0), "z", 3)
