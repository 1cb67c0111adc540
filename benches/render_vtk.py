"""VTK's ray casters on the same volume, view and transfer function as `benches/render.rs`.

Reads a job JSON written by the Rust bench (volume path, camera, TF in data units, size, step,
shading) and sets up vtkFixedPointVolumeRayCastMapper (VTK's CPU ray caster) and, unless the job
says `"gpu": false`, vtkGPUVolumeRayCastMapper (OpenGL; on a machine without a GPU it runs on
Mesa's llvmpipe), each in its own offscreen window, rendered once to warm up. Then it serves
commands on stdin, one per line, so the bench can interleave VTK's frames with its own:

- `mappers`: prints the mapper names as a JSON list;
- `frame NAME`: renders one frame with mapper NAME and prints `{"ms": wall, "cpu_ms": process
  CPU time}` (process CPU time counts VTK's and llvmpipe's threads: it is far less sensitive to
  other processes on a shared machine than the wall time);
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


def volume_property(job, sp):
    prop = vtk.vtkVolumeProperty()
    col = vtk.vtkColorTransferFunction()
    for x, r, g, b in job["color"]:
        col.AddRGBPoint(x, r, g, b)
    op = vtk.vtkPiecewiseFunction()
    for x, a in job["opacity"]:
        op.AddPoint(x, a)
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


def image_data(job):
    img = nib.load(job["volume"])
    data = np.asarray(img.dataobj, dtype=np.float32)
    if data.ndim > 3:
        data = data[..., 0]
    dims = data.shape
    sp = job["spacing"]
    vi = vtk.vtkImageData()
    vi.SetDimensions(*dims)
    vi.SetSpacing(*sp)
    vi.SetOrigin(*[-(d - 1) / 2 * s for d, s in zip(dims, sp)])
    arr = numpy_support.numpy_to_vtk(data.ravel(order="F"), deep=True, array_type=vtk.VTK_FLOAT)
    vi.GetPointData().SetScalars(arr)
    return vi, sp


def setup(job, vi, sp, mapper):
    """A window rendering `mapper` over the job's volume and camera, rendered once."""
    prop = volume_property(job, sp)
    mapper.SetInputData(vi)
    mapper.SetAutoAdjustSampleDistances(0)
    mapper.SetSampleDistance(job["step"] * min(sp))
    if hasattr(mapper, "SetImageSampleDistance"):
        mapper.SetImageSampleDistance(1.0)
    if hasattr(mapper, "SetNumberOfThreads"):
        mapper.SetNumberOfThreads(job.get("threads", 2))
    vol = vtk.vtkVolume()
    vol.SetMapper(mapper)
    vol.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddVolume(vol)
    cam = ren.GetActiveCamera()
    cam.SetPosition(*job["eye"])
    cam.SetFocalPoint(0, 0, 0)
    cam.SetViewUp(*job["up"])
    cam.SetViewAngle(job["fov"])
    ren.ResetCameraClippingRange()
    rw = vtk.vtkRenderWindow()
    rw.SetOffScreenRendering(1)
    rw.AddRenderer(ren)
    rw.SetSize(job["width"], job["height"])
    rw.Render()  # warm-up: uploads, allocations, gradient encoding
    return rw, vol


def main(job_path):
    job = json.load(open(job_path))
    vi, sp = image_data(job)
    mappers = [("vtk-fixedpoint-cpu", vtk.vtkFixedPointVolumeRayCastMapper())]
    if job.get("gpu", True):
        mappers.append(("vtk-gpu-opengl", vtk.vtkGPUVolumeRayCastMapper()))
    windows = {name: setup(job, vi, sp, m) for name, m in mappers}
    print(json.dumps({"ready": [n for n, _ in mappers]}), flush=True)
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "quit":
            break
        if cmd[0] == "frame":
            rw, vol = windows[cmd[1]]
            vol.Modified()
            c = time.process_time()
            t = time.perf_counter()
            rw.Render()
            ms = 1000 * (time.perf_counter() - t)
            cpu = 1000 * (time.process_time() - c)
            print(json.dumps({"ms": ms, "cpu_ms": cpu}), flush=True)
        elif cmd[0] == "save":
            rw, _ = windows[cmd[1]]
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
