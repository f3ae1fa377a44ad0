"""pi0's offline hub fixture: `lerobot/pi0_libero_finetuned_v044` as lerobot 0.6.1 saves a
LIBERO-finetuned `PI0Policy` (reduced widths), with PaliGemma's tokenizer."""

from vlaquantbench.hub.fixture import HubFixture
from vlaquantbench.hub.tokenizer import REPO_ID, write_libero_paligemma_tokenizer
from vlaquantbench.models.pi0.adapter import Pi0Adapter
from vlaquantbench.models.pi_family_fixture import write_pi_checkpoint

FIXTURE = HubFixture(
    tokenizers={REPO_ID: write_libero_paligemma_tokenizer},
    write_checkpoint=lambda folder, seed: write_pi_checkpoint(
        folder, Pi0Adapter, "lerobot.policies.pi0.processor_pi0:make_pi0_pre_post_processors",
        {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"}, seed,
    ),
)
