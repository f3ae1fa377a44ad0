"""benchmarks/simstack.py carries the GL loaders a real EGL context maps (a GPU machine may have only
its vendor's library): found in a child that renders, by soname, without any vendor library."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import simstack  # noqa: E402

_RENDER = """
import json, mujoco
model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
with mujoco.Renderer(model, 16, 16) as renderer:
    renderer.update_scene(mujoco.MjData(model))
    assert renderer.render().shape == (16, 16, 3)
    print(json.dumps(sorted({line.split()[-1] for line in open("/proc/self/maps") if ".so" in line})))
"""


def test_gl_loaders_of_an_egl_render_are_the_vendor_neutral_ones():
    out = subprocess.run([sys.executable, "-c", _RENDER], env={**os.environ, "MUJOCO_GL": "egl"},
                         capture_output=True, text=True, check=True)
    mapped = json.loads(out.stdout.splitlines()[-1])
    loaders = simstack.gl_loaders(mapped)
    assert {"libEGL.so.1", "libGLdispatch.so.0"} <= set(loaders), mapped
    assert all(path.is_file() and path.name.startswith(soname) for soname, path in loaders.items())
    vendors = [p for p in mapped if "_mesa" in p or "_nvidia" in p]
    assert vendors, "the render should have mapped a vendor library too"
    assert not set(vendors) & {str(p) for p in loaders.values()}
