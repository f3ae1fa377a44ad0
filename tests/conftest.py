"""Session fixtures shared by test modules (expensive built artefacts, built once per run), and the suite's order."""

import pytest
import yaml

from paths import ROOT


def pytest_collection_modifyitems(items):
    """The SLURM cluster test runs last. It installs Debian's slurm client and stops its cluster after
    it, and from then on every Snakemake start waits ~9 s: the SLURM executor plugin runs `scontrol show
    config` when Snakemake loads it, and scontrol retries the stopped controller for MessageTimeout
    (10 s) before giving up (`snakemake -n` here: 11.2 s instead of 2.2 s). Stable: the rest keep their order."""
    items.sort(key=lambda item: item.path.name == "test_slurm_cluster.py")


@pytest.fixture(scope="session")
def hub_fixture(tmp_path_factory):
    """The offline hub fixture of config/paper_smoke.yaml's checkpoints (`vqb hub-fixture`):
    {"home": HF_HOME folder, "repos": {repo id: {revision, path}}, "study": the config's study}."""
    from vlaquantbench.hub.fixture import build_hub_fixture, full_variant_models

    study = yaml.safe_load((ROOT / "config" / "paper_smoke.yaml").read_text())["study"]
    home = tmp_path_factory.mktemp("hf_home")
    return {"home": home, "repos": build_hub_fixture(home, full_variant_models(study)), "study": study}
