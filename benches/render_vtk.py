"""VTK's ray casters on the same volume, view and transfer function as `benches/render.rs`.

Reads a job JSON written by the Rust bench (volume path, camera, TF in data units, size, step,
shading), renders offscreen with vtkFixedPointVolumeRayCastMapper (VTK's CPU ray caster) and
vtkGPUVolumeRayCastMapper (OpenGL; on a machine without a GPU it runs on Mesa's llvmpipe), and
prints one JSON line per mapper with the median milliseconds per frame; writes each image as PNG.
Needs `pip install vtk nibabel numpy`.
"""
import json
import sys
import time

import nibabel as nib
import numpy as np
import vtk
from vtk.util import numpy_support


def main(job_path):
    job = json.load(open(job_path))
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
    out = []
    for name, mapper in [
        ("vtk-fixedpoint-cpu", vtk.vtkFixedPointVolumeRayCastMapper()),
        ("vtk-gpu-opengl", vtk.vtkGPUVolumeRayCastMapper()),
    ]:
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
        rw.Render()  # warm-up: uploads, allocations
        times = []
        for _ in range(job["frames"]):
            vol.Modified()
            t = time.perf_counter()
            rw.Render()
            times.append(time.perf_counter() - t)
        w2i = vtk.vtkWindowToImageFilter()
        w2i.SetInput(rw)
        w2i.ReadFrontBufferOff()
        w2i.Update()
        pw = vtk.vtkPNGWriter()
        pw.SetFileName(job["out_prefix"] + name + ".png")
        pw.SetInputConnection(w2i.GetOutputPort())
        pw.Write()
        times.sort()
        out.append({"mapper": name, "ms": 1000 * times[len(times) // 2],
                    "renderer": rw.GetClassName()})
    for o in out:
        print(json.dumps(o))


if __name__ == "__main__":
    main(sys.argv[1])
