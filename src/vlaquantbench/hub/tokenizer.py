"""A small tokenizer in the on-disk format and class of PaliGemma's (`google/paligemma-3b-pt-224`).

The released pi0/pi0.5 processors load that repository with `AutoTokenizer`, which resolves the
repository's `config.json` (model type `paligemma`) and `tokenizer_config.json` (class
`GemmaTokenizer`, transformers' tokenizers-backed Gemma class) and reads `tokenizer.json`: a BPE model
with byte fallback over SentencePiece-style pieces (spaces become "▁"), Gemma's special tokens at ids
0-4, bos prepended, and PaliGemma's added `<image>` token. This one has the same structure with a
vocabulary trained locally (`tokenizers`' BPE trainer) on the prompts the policies build (`training_corpus`): the
task instructions a model's hub fixture gives (its released checkpoint's benchmark's), pi0.5's
"Task: ..., State: ...;\\nAction: " frame and the 256 state bins.
"""

from __future__ import annotations

import json
from pathlib import Path

REPO_ID = "google/paligemma-3b-pt-224"
SPECIAL_TOKENS = ("<pad>", "<eos>", "<bos>", "<unk>", "<mask>")  # Gemma's ids 0-4
IMAGE_TOKEN = "<image>"  # PaliGemma's addition to the Gemma vocabulary
VOCAB_SIZE = 1024


def training_corpus(instructions: list[str]) -> list[str]:
    """The prompts the policies build from `instructions`: each one alone and in pi0.5's frame."""
    bins = " ".join(str(b) for b in range(256))
    return [*instructions, *(f"Task: {text}, State: {bins};\nAction: " for text in instructions)]


def write_paligemma_tokenizer(folder: str | Path, corpus: list[str], vocab_size: int = VOCAB_SIZE) -> Path:
    """Train the vocabulary on `corpus` and save tokenizer and model config as the repository holds them."""
    from tokenizers import Tokenizer, models, normalizers, trainers
    from transformers import GemmaTokenizer, PaliGemmaConfig

    trainer_model = Tokenizer(models.BPE(unk_token="<unk>", byte_fallback=True))
    trainer_model.normalizer = normalizers.Replace(" ", "▁")
    trainer_model.train_from_iterator(corpus, trainers.BpeTrainer(vocab_size=vocab_size, show_progress=False))
    trained = json.loads(trainer_model.to_str())["model"]
    # Gemma's layout: special tokens, then the 256 byte-fallback pieces, then the learned pieces.
    pieces = [*SPECIAL_TOKENS, *(f"<0x{b:02X}>" for b in range(256))]
    pieces += [p for p, _ in sorted(trained["vocab"].items(), key=lambda item: item[1]) if p not in pieces]
    merges = [tuple(m.split(" ", 1)) if isinstance(m, str) else tuple(m) for m in trained["merges"]]
    tokenizer = GemmaTokenizer(vocab={p: i for i, p in enumerate(pieces)}, merges=merges, add_bos_token=True)
    tokenizer.add_tokens([IMAGE_TOKEN], special_tokens=True)
    folder = Path(folder)
    tokenizer.save_pretrained(folder)
    PaliGemmaConfig().save_pretrained(folder)
    return folder
