"""VTK's ray casters on the same volume, views and transfer function as `benches/render.rs`.

Reads a job JSON written by the Rust bench (volume path, camera, TF in data units, size, step,
shading, threads) and sets up vtkFixedPointVolumeRayCastMapper (VTK's CPU ray caster) and,
unless the job says `"gpu": false`, vtkGPUVolumeRayCastMapper (OpenGL; on a machine without a
GPU it runs on Mesa's llvmpipe), each in its own offscreen window, rendered once to warm up.

The volume goes to VTK in the file's own integer type, narrowed without loss to the smallest of
uint8, int8, uint16 and int16 that holds every value (the fixed-point caster's fast path: it
indexes its tables by the 8- or 16-bit value; floats would be rescaled per sample). A file with
a non-identity NIfTI scaling keeps its stored integers and the TF's control points are mapped
back through the scaling instead. The job may force `"dtype": "float32"` (the old, slower set-up).

Then it serves commands on stdin, one per line, so the bench can interleave VTK's frames with
its own:

- `frame NAME [ex ey ez ux uy uz]`: moves the camera (eye, view-up; focal point at the centre)
  when given, renders one frame with mapper NAME and prints
  `{"ms", "cpu_ms", "cast_ms", "cast_cpu_ms"}`: the wall and process CPU time of the whole
  `Render()` (what a VTK user waits for: ray set-up, the threaded ray cast, the blit of the
  image through OpenGL and the swap), and, for the fixed-point caster, of the ray cast alone,
  between the mapper's own `VolumeMapperRenderStartEvent` and `VolumeMapperRenderEndEvent`
  (around `RenderSubVolume`: the threaded cast into its image, without the per-frame ray set-up
  and the blit). Process CPU time counts VTK's and llvmpipe's threads;
- `save NAME PATH`: writes mapper NAME's last image as PNG;
- `quit`.

Needs `pip install vtk nibabel numpy`.
"""
import json
import sys
import time

import nibabel as nib
import numpy as np
import vtk
from vtk.util import numpy_support

NARROW = [np.uint8, np.int8, np.uint16, np.int16]


def volume_property(job, sp, to_stored):
    prop = vtk.vtkVolumeProperty()
    col = vtk.vtkColorTransferFunction()
    for x, r, g, b in job["color"]:
        col.AddRGBPoint(to_stored(x), r, g, b)
    op = vtk.vtkPiecewiseFunction()
    for x, a in job["opacity"]:
        op.AddPoint(to_stored(x), a)
    prop.SetColor(col)
    prop.SetScalarOpacity(op)
    prop.SetInterpolationTypeToLinear()
    prop.SetScalarOpacityUnitDistance(min(sp))
    sh = job.get("shading")
    if sh:
        prop.ShadeOn()
        prop.SetAmbient(sh["ambient"])
        prop.SetDiffuse(sh["diffuse"])
        prop.SetSpecular(sh["specular"])
        prop.SetSpecularPower(sh["shininess"])
    return prop


def stored_data(job):
    """The voxels as VTK gets them, the dtype's name, and the map from data units to them."""
    img = nib.load(job["volume"])
    if job.get("dtype") == "float32":
        data = np.asarray(img.dataobj, dtype=np.float32)
        to_stored = float
    else:
        data = np.asarray(img.dataobj.get_unscaled())
        slope, inter = img.dataobj.slope, img.dataobj.inter
        slope = 1.0 if not np.isfinite(slope) or slope == 0 else float(slope)
        inter = 0.0 if not np.isfinite(inter) else float(inter)

        def to_stored(x):
            return (x - inter) / slope

        if np.issubdtype(data.dtype, np.integer):
            lo, hi = int(data.min()), int(data.max())
            for t in NARROW:
                if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max:
                    data = data.astype(t)
                    break
    if data.ndim > 3:
        data = data[..., 0]
    return np.ascontiguousarray(data), data.dtype.name, to_stored


def image_data(job):
    data, dtype, to_stored = stored_data(job)
    dims = data.shape
    sp = job["spacing"]
    vi = vtk.vtkImageData()
    vi.SetDimensions(*dims)
    vi.SetSpacing(*sp)
    vi.SetOrigin(*[-(d - 1) / 2 * s for d, s in zip(dims, sp)])
    arr = numpy_support.numpy_to_vtk(data.ravel(order="F"), deep=True)
    vi.GetPointData().SetScalars(arr)
    return vi, sp, dtype, to_stored


class CastTimer:
    """Wall and process CPU time between a mapper's ray-cast start and end events."""

    def __init__(self, mapper):
        self.start = None
        self.ms = float("nan")
        self.cpu_ms = float("nan")
        mapper.AddObserver(vtk.vtkCommand.VolumeMapperRenderStartEvent, self.on_start)
        mapper.AddObserver(vtk.vtkCommand.VolumeMapperRenderEndEvent, self.on_end)

    def on_start(self, *_):
        self.start = (time.perf_counter(), time.process_time())

    def on_end(self, *_):
        if self.start:
            t, c = self.start
            self.ms = 1000 * (time.perf_counter() - t)
            self.cpu_ms = 1000 * (time.process_time() - c)
            self.start = None


def setup(job, vi, sp, to_stored, mapper):
    """A window rendering `mapper` over the job's volume and camera, rendered once."""
    prop = volume_property(job, sp, to_stored)
    mapper.SetInputData(vi)
    mapper.SetAutoAdjustSampleDistances(0)
    mapper.SetSampleDistance(job["step"] * min(sp))
    if hasattr(mapper, "SetImageSampleDistance"):
        mapper.SetImageSampleDistance(1.0)
    if hasattr(mapper, "SetNumberOfThreads"):
        mapper.SetNumberOfThreads(job.get("threads", 2))
    timer = CastTimer(mapper) if isinstance(mapper, vtk.vtkFixedPointVolumeRayCastMapper) else None
    vol = vtk.vtkVolume()
    vol.SetMapper(mapper)
    vol.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddVolume(vol)
    cam = ren.GetActiveCamera()
    cam.SetFocalPoint(0, 0, 0)
    cam.SetViewAngle(job["fov"])
    rw = vtk.vtkRenderWindow()
    rw.SetOffScreenRendering(1)
    rw.AddRenderer(ren)
    rw.SetSize(job["width"], job["height"])
    place(ren, job["eye"], job["up"])
    rw.Render()  # warm-up: uploads, allocations, gradient encoding
    return rw, ren, vol, timer


def place(ren, eye, up):
    cam = ren.GetActiveCamera()
    cam.SetPosition(*eye)
    cam.SetViewUp(*up)
    ren.ResetCameraClippingRange()


def main(job_path):
    job = json.load(open(job_path))
    vi, sp, dtype, to_stored = image_data(job)
    mappers = [("vtk-fixedpoint-cpu", vtk.vtkFixedPointVolumeRayCastMapper())]
    if job.get("gpu", True):
        mappers.append(("vtk-gpu-opengl", vtk.vtkGPUVolumeRayCastMapper()))
    windows = {name: setup(job, vi, sp, to_stored, m) for name, m in mappers}
    print(json.dumps({"ready": [n for n, _ in mappers], "dtype": dtype,
                      "vtk": vtk.vtkVersion.GetVTKVersion()}), flush=True)
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "quit":
            break
        if cmd[0] == "frame":
            rw, ren, vol, timer = windows[cmd[1]]
            if len(cmd) == 8:
                v = [float(x) for x in cmd[2:]]
                place(ren, v[:3], v[3:])
            vol.Modified()
            c = time.process_time()
            t = time.perf_counter()
            rw.Render()
            ms = 1000 * (time.perf_counter() - t)
            cpu = 1000 * (time.process_time() - c)
            out = {"ms": ms, "cpu_ms": cpu}
            if timer:
                out.update(cast_ms=timer.ms, cast_cpu_ms=timer.cpu_ms)
            print(json.dumps(out), flush=True)
        elif cmd[0] == "save":
            rw = windows[cmd[1]][0]
            w2i = vtk.vtkWindowToImageFilter()
            w2i.SetInput(rw)
            w2i.ReadFrontBufferOff()
            w2i.Update()
            pw = vtk.vtkPNGWriter()
            pw.SetFileName(cmd[2])
            pw.SetInputConnection(w2i.GetOutputPort())
            pw.Write()
            print(json.dumps({"saved": cmd[2]}), flush=True)
        else:
            print(json.dumps({"error": f"unknown command {cmd[0]}"}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
