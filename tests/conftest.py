"""Session fixtures shared by test modules: expensive built artefacts, built once per run."""

import json
import subprocess
import sys

import pytest
import yaml

from paths import ROOT

TRAINED_HOME = ROOT / "checkpoints" / "pi05_metaworld_cpu"  # a plain checkpoint folder, committed (docs/checkpoints.md, "Trained on the CPU")


@pytest.fixture(scope="session")
def hub_fixture(tmp_path_factory):
    """The offline hub fixture of config/paper_smoke.yaml's checkpoints (`vqb hub-fixture`):
    {"home": HF_HOME folder, "repos": {repo id: {revision, path}}, "study": the config's study}."""
    from vlaquantbench.hub.fixture import build_hub_fixture, full_variant_models

    study = yaml.safe_load((ROOT / "config" / "paper_smoke.yaml").read_text())["study"]
    home = tmp_path_factory.mktemp("hf_home")
    return {"home": home, "repos": build_hub_fixture(home, full_variant_models(study)), "study": study}


@pytest.fixture(scope="session")
def trained_policy(tmp_path_factory):
    """The pi0.5 trained here on the CPU, loaded as a study loads a released checkpoint: the checkpoint rule's
    stamp (`download_checkpoint`: TRAINED_HOME verified, at the revision its training.json names) and the
    pi0.5 adapter on the CPU in float32, executing the chunk it was trained with.
    {"home", "training": training.json, "stamp": the stamp file, "adapter": loaded}; quantize a deep copy."""
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter
    from vlaquantbench.runner.checkpoint import download_checkpoint

    training = json.loads((TRAINED_HOME / "training.json").read_text())
    stamp = tmp_path_factory.mktemp("trained_policy") / "checkpoint.json"
    folder = download_checkpoint("pi05", "full", training["checkpoint"], training["revision"], stamp, TRAINED_HOME)["path"]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=training["checkpoint"],
                                         revision=training["revision"], checkpoint_dir=folder, device="cpu",
                                         dtype="float32", executed_chunk=training["policy"]["n_action_steps"]))
    adapter.load()
    return {"home": TRAINED_HOME, "training": training, "stamp": stamp, "adapter": adapter}


@pytest.fixture(scope="session")
def demonstrations_run(tmp_path_factory):
    """`snakemake --cores 2 results/demos/manifest.tsv checkpoints/tiny/training.json` in a fresh working folder with
    tests/demonstrations_workflow.py's sections: rule demonstrations, then rule train_policy on its dataset (one run
    for tests/test_demonstrations.py and tests/test_training.py). {"workdir", "out": the demonstrations' folder}."""
    import demonstrations_workflow as sections

    workdir = tmp_path_factory.mktemp("demos")
    (workdir / "demos.yaml").write_text(yaml.safe_dump({"demonstrations": sections.DEMONSTRATIONS,
                                                        "training": sections.TRAINING}))
    command = [sys.executable, "-m", "snakemake", *sections.TARGETS, "--cores", "2",
               "--snakefile", str(ROOT / "Snakefile"), "--directory", str(workdir),
               # the Snakefile's own config file is found relative to the working folder: named here
               "--configfile", str(ROOT / "config" / "config.yaml"), str(workdir / "demos.yaml")]
    run = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    return {"workdir": workdir, "out": workdir / sections.DEMONSTRATIONS["dir"]}
