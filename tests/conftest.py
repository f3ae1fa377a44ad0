"""Session fixtures shared by test modules: expensive built artefacts, built once per run."""

import pytest
import yaml

from paths import ROOT


@pytest.fixture(scope="session")
def hub_fixture(tmp_path_factory):
    """The offline hub fixture of config/paper_smoke.yaml's checkpoints (`vqb hub-fixture`):
    {"home": HF_HOME folder, "repos": {repo id: {revision, path}}, "study": the config's study}."""
    from vlaquantbench.hub.fixture import build_hub_fixture, full_variant_models

    study = yaml.safe_load((ROOT / "config" / "paper_smoke.yaml").read_text())["study"]
    home = tmp_path_factory.mktemp("hf_home")
    return {"home": home, "repos": build_hub_fixture(home, full_variant_models(study)), "study": study}
