"""A LeRobotDataset of demonstrations held on the training device, with every frame's model inputs
computed once by the policy's own preprocessor.

lerobot's `LeRobotDataset.__getitem__` decodes a PNG and gathers the action chunk of one frame per
call; on a GPU that held training at 0.29 s a step (batch 128, 224 px, 12 loader workers). A
demonstration set this size fits in device memory as uint8 (30,000 frames at 112 px: 1.1 GB), and
everything the policy's preprocessor derives from a frame is fixed by the dataset's statistics: the
normalized action chunk and the prompt's tokens (the task and the state's 256 bins). So `DeviceFrames`
decodes every image once, builds each frame's action chunk as lerobot's delta timestamps do (indices
clamped to the episode: `DatasetReader._get_query_indices`), runs the real preprocessor over all
frames in blocks, and keeps the results on the device. A batch is then one gather, plus the random
shift image policies train with on Meta-World (DrQ's: pad by replicating the border, crop back at a
random offset per sample).
"""

from __future__ import annotations

import torch

# Frames decoded and preprocessed at a time while loading.
LOAD_BLOCK = 2048


class DeviceFrames:
    """Every frame of a LeRobotDataset as the policy's preprocessor hands it to the policy, on `device`:
    `images` uint8 [N, 3, H, W], `tokens` and `attention_mask` [N, L], `actions` [N, chunk, dim]."""

    def __init__(self, dataset, preprocessor, chunk_size: int, device: torch.device):
        from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE

        meta = dataset.meta
        hf = dataset.hf_dataset
        starts = torch.as_tensor(meta.episodes["dataset_from_index"])
        ends = torch.as_tensor(meta.episodes["dataset_to_index"])
        episode = _column(hf, "episode_index").long()
        index = _column(hf, "index").long()
        offsets = torch.arange(chunk_size)
        # lerobot's delta timestamps: frame i's chunk is frames i.. i+chunk-1, clamped to its episode's last.
        chunk_rows = torch.minimum(index[:, None] + offsets, ends[episode][:, None] - 1) - starts[0]
        if (chunk_rows < 0).any() or (chunk_rows >= len(hf)).any():
            raise ValueError("the dataset's frame indices are not one contiguous range (a subset of its episodes?)")
        actions = _column(hf, ACTION)
        states = _column(hf, OBS_STATE)
        task_of = dict(zip(meta.tasks["task_index"], meta.tasks.index))
        tasks = [task_of[int(t)] for t in _column(hf, "task_index")]
        blocks = {"images": [], "tokens": [], "masks": [], "actions": []}
        for first in range(0, len(hf), LOAD_BLOCK):
            rows = slice(first, min(first + LOAD_BLOCK, len(hf)))
            images = torch.stack(hf[rows][OBS_IMAGE])  # float [0, 1], lerobot's `hf_transform_to_torch`
            processed = preprocessor({OBS_IMAGE: images, OBS_STATE: states[rows], ACTION: actions[chunk_rows[rows]],
                                      "task": tasks[rows]})
            blocks["images"].append((images * 255).round().to(torch.uint8).to(device))
            blocks["tokens"].append(processed[OBS_LANGUAGE_TOKENS].to(device))
            blocks["masks"].append(processed[OBS_LANGUAGE_ATTENTION_MASK].to(device))
            blocks["actions"].append(processed[ACTION].to(device))
        self.images, self.tokens, self.attention_mask, self.actions = (
            torch.cat(blocks[key]) for key in ("images", "tokens", "masks", "actions"))
        self.keys = OBS_IMAGE, OBS_LANGUAGE_TOKENS, OBS_LANGUAGE_ATTENTION_MASK, ACTION
        self.device = device

    def __len__(self) -> int:
        return len(self.images)

    def batch(self, rows: torch.Tensor, shift_px: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The policy's input for frames `rows`: images as float [0, 1], randomly shifted by up to
        `shift_px` pixels each way (0: unchanged)."""
        images = self.images[rows]
        if shift_px:
            images = random_shift(images, shift_px, generator)
        image, tokens, mask, action = self.keys
        return {image: images.float() / 255, tokens: self.tokens[rows], mask: self.attention_mask[rows],
                action: self.actions[rows]}


def _column(hf_dataset, key: str) -> torch.Tensor:
    """A numeric column of the dataset's Arrow table ([N] or [N, dim]), without per-row Python objects."""
    import numpy as np

    column = hf_dataset.data.column(key).combine_chunks()
    if hasattr(column, "flatten"):  # a list column: one fixed-size vector a frame
        return torch.from_numpy(np.asarray(column.flatten()).reshape(len(column), -1).copy())
    return torch.from_numpy(np.asarray(column).copy())


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ's augmentation on a batch [B, C, H, W]: pad each side by `pad` pixels replicating the
    border, then crop the original size at an offset drawn per sample (one gather, no per-sample loop)."""
    batch, channels, height, width = images.shape
    padded = torch.nn.functional.pad(images.float(), (pad, pad, pad, pad), mode="replicate").to(images.dtype)
    offsets = torch.randint(0, 2 * pad + 1, (2, batch), device=images.device, generator=generator)
    rows = (offsets[0][:, None] + torch.arange(height, device=images.device))[:, None, :, None]
    cols = (offsets[1][:, None] + torch.arange(width, device=images.device))[:, None, None, :]
    samples = torch.arange(batch, device=images.device)[:, None, None, None]
    return padded[samples, torch.arange(channels, device=images.device)[None, :, None, None], rows, cols]
