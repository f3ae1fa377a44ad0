"""benchmarks/simstack.py carries the GL loaders a real EGL context maps (a GPU machine may have only
its vendor's library): found in a child that renders, by soname, without any vendor library."""

import importlib.metadata
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


# What the GPU machine has itself: `simstack.PRESENT`, and the CUDA libraries its torch came with.
TORCH_CUDA = {"nvidia", "cuda"}

_LOAD = """
import json, sys
sys.path[:0] = sys.argv[1:4]  # the project's code, the unpacked pack, the machine's own packages
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
import jsonschema, lerobot, transformers
adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
adapter.load()
print(json.dumps({"lerobot": lerobot.__file__, "transformers": transformers.__file__, "jsonschema": jsonschema.__file__}))
"""


def machine_view(folder: Path) -> Path:
    """A folder of links to the entries of this environment's site-packages that the GPU machine has itself:
    the present top-level modules, their distributions' metadata and bundled libraries."""
    present = (simstack.PRESENT - simstack.CARRY_ALWAYS) | TORCH_CUDA
    by_top = importlib.metadata.packages_distributions()
    dists = {d.lower().replace("-", "_") for top in present for d in by_top.get(top, ())}
    folder.mkdir()
    for entry in simstack._site_packages().iterdir():
        name = entry.name
        if name.endswith(".dist-info"):
            keep = name.split("-")[0].lower() in dists
        elif name.endswith(".libs"):
            keep = name[:-5].lower().replace("-", "_") in dists or name[:-5] in present
        else:
            keep = name.split(".")[0] in present
        if keep:
            (folder / name).symlink_to(entry)
    return folder


def test_the_policy_pack_alone_loads_a_policy_beside_only_the_machines_own_packages(tmp_path):
    parts = simstack.pack_policy(tmp_path / "pack")
    manifest = json.loads((parts[0] / "manifest.json").read_text())
    assert {"lerobot", "transformers", "tokenizers", "jsonschema"} <= set(manifest["dists"]), manifest["dists"]
    assert not {"torch", "numpy", "datasets", "av"} & set(manifest["dists"])
    simstack.unpack(tmp_path / "pack", tmp_path / "sim")
    unpacked = tmp_path / "sim" / "site"
    # -S: no site-packages but the ones named (nor the project's editable install)
    out = subprocess.run([sys.executable, "-S", "-c", _LOAD, str(ROOT / "src"), str(unpacked),
                          str(machine_view(tmp_path / "machine"))], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    loaded = json.loads(out.stdout.splitlines()[-1])
    assert all(path.startswith(str(unpacked)) for path in loaded.values()), loaded


def test_a_package_neither_carried_nor_on_the_machine_is_missing_in_that_view(tmp_path):
    out = subprocess.run([sys.executable, "-S", "-c", "import sys; sys.path[:0] = sys.argv[1:]; import lerobot",
                          str(machine_view(tmp_path / "machine"))], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "No module named 'lerobot'" in out.stderr, out.stderr[-2000:]
