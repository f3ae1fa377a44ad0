"""bitsandbytes kernels (an optional extra): `nf4` (4-bit NormalFloat) and `int8` (LLM.int8())."""

from __future__ import annotations

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.kernels.packed import replace_all, require_preset


def _bnb_linear(linear: nn.Linear, kind: str) -> nn.Module:
    try:
        import bitsandbytes as bnb
    except ImportError as err:
        raise UserError(f"method {kind!r} needs bitsandbytes: pip install 'vlaquantbench[kernels]'") from err
    device = linear.weight.device
    has_bias = linear.bias is not None
    if kind == "nf4":
        module = bnb.nn.Linear4bit(linear.in_features, linear.out_features, bias=has_bias,
                                   compute_dtype=torch.bfloat16, quant_type="nf4", device="meta")
        module.weight = bnb.nn.Params4bit(linear.weight.detach(), requires_grad=False, quant_type="nf4")
    else:
        module = bnb.nn.Linear8bitLt(linear.in_features, linear.out_features, bias=has_bias,
                                     has_fp16_weights=False, threshold=6.0, device="meta")
        module.weight = bnb.nn.Int8Params(linear.weight.detach(), requires_grad=False, has_fp16_weights=False)
    if has_bias:
        module.bias = nn.Parameter(linear.bias.detach(), requires_grad=False)
    return module.to(device)  # bitsandbytes quantizes on the move to a CUDA device


def nf4(model, selection, config):
    require_preset(config, "nf4")
    return replace_all(model, selection, lambda n, m: _bnb_linear(m, "nf4"),
                        "bitsandbytes NF4 (4-bit NormalFloat, block 64, bf16 compute)")


def llm_int8(model, selection, config):
    require_preset(config, "int8")
    return replace_all(model, selection, lambda n, m: _bnb_linear(m, "int8"),
                        "bitsandbytes LLM.int8() (int8 row-wise weights, fp16 outlier columns above 6.0)")
