"""pi0's offline hub fixture: `lerobot/pi0_libero_finetuned_v044` as lerobot 0.6.1 saves a
LIBERO-finetuned `PI0Policy` (reduced widths), with PaliGemma's tokenizer."""

from vlaquantbench.models.pi0.adapter import Pi0Adapter
from vlaquantbench.models.pi_family_fixture import pi_fixture

FIXTURE = pi_fixture(Pi0Adapter, "lerobot.policies.pi0.processor_pi0:make_pi0_pre_post_processors")
