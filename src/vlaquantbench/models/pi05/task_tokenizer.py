"""A word-level tokenizer made for a trained policy's task descriptions, shipped with the checkpoint.

PaliGemma's tokenizer has 257,152 entries; its embedding alone would outweigh a small policy trained
here many times over. pi0.5's prompt is `Task: <description>, State: <b1> ... <bn>;\\nAction: ` with
each state dimension discretized into one of 256 bins (lerobot's
`Pi05PrepareStateTokenizerProcessorStep`), so a vocabulary of the descriptions' words, the frame's
words and punctuation, and the numbers 0-255 tokenizes every prompt of those tasks with no unknown
token. It is a `tokenizers` WordLevel model (lower-cased, split on whitespace and punctuation, bos
prepended as PaliGemma's is) wrapped as transformers' `PreTrainedTokenizerFast`, so the checkpoint's
preprocessor loads it by repository id with `AutoTokenizer`, as it loads PaliGemma's.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

SPECIAL_TOKENS = ("<pad>", "<eos>", "<bos>", "<unk>")  # Gemma's order of ids 0-3
# The words and punctuation of pi0.5's prompt frame (lerobot's Pi05PrepareStateTokenizerProcessorStep).
PROMPT_FRAME = "Task: , State: ;\nAction: "
STATE_BINS = 256
# The embedding's rows are padded to a multiple of this (tensor-core friendly shapes).
VOCAB_MULTIPLE = 64


def _words(text: str) -> list[str]:
    # The Whitespace pre-tokenizer's split (`\w+|[^\w\s]+`) after lower-casing.
    return re.findall(r"\w+|[^\w\s]+", text.lower())


def vocabulary(descriptions: Iterable[str]) -> list[str]:
    """Special tokens, the frame's and the descriptions' words (sorted), then any bin number not yet in."""
    words = sorted({w for text in [PROMPT_FRAME, *descriptions] for w in _words(text)})
    bins = [str(b) for b in range(STATE_BINS) if str(b) not in words]
    return [*SPECIAL_TOKENS, *words, *bins]


def padded_vocab_size(tokenizer) -> int:
    """The embedding rows a model needs for `tokenizer`: its length rounded up to VOCAB_MULTIPLE."""
    return -(-len(tokenizer) // VOCAB_MULTIPLE) * VOCAB_MULTIPLE


def build_task_tokenizer(descriptions: Iterable[str]):
    """The `PreTrainedTokenizerFast` of `descriptions`' vocabulary."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {token: i for i, token in enumerate(vocabulary(descriptions))}
    tokenizer = Tokenizer(models.WordLevel(vocab=vocab, unk_token="<unk>"))
    tokenizer.normalizer = normalizers.Lowercase()
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer.post_processor = processors.TemplateProcessing(single="<bos> $A", special_tokens=[("<bos>", vocab["<bos>"])])
    return PreTrainedTokenizerFast(tokenizer_object=tokenizer, pad_token="<pad>", eos_token="<eos>",
                                   bos_token="<bos>", unk_token="<unk>")


def write_task_tokenizer(folder: str | Path, descriptions: Iterable[str]) -> Path:
    """Save the tokenizer of `descriptions` into `folder` (tokenizer.json, tokenizer_config.json, config.json, ...)."""
    from transformers import PretrainedConfig

    folder = Path(folder)
    build_task_tokenizer(descriptions).save_pretrained(folder)
    # AutoTokenizer reads a repository's config.json before its tokenizer_config.json; a generic one
    # (no model type) leaves the choice of class to tokenizer_config.json.
    PretrainedConfig().save_pretrained(folder)
    return folder
