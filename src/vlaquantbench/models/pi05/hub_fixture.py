"""pi0.5's offline hub fixture: `lerobot/pi05_libero_finetuned_v044` as lerobot 0.6.1 saves a
LIBERO-finetuned `PI05Policy` (reduced widths), with PaliGemma's tokenizer.

Normalization MEAN_STD, not lerobot's pi0.5 default QUANTILES: the mode the released LIBERO
finetune's policy_preprocessor.json is reported to carry (README, "Offline hub fixture")."""

from vlaquantbench.models.pi05.adapter import Pi05Adapter
from vlaquantbench.models.pi_family_fixture import pi_fixture

FIXTURE = pi_fixture(Pi05Adapter, "lerobot.policies.pi05.processor_pi05:make_pi05_pre_post_processors")
