"""The version of the quantization arithmetic, declared by hand.

Bump `QUANT_SEMANTICS` in the commit that changes what a quantized policy computes (a grid's rounding,
a group size default, where activations are quantized, a calibration statistic): it enters every cell's
hash and header, so cells of the new arithmetic get new folders, a killed cell of the old one is not
resumed by the new code, and a table mixing both says so. Commits that do not change the arithmetic
(refactors, speed, logging) leave it alone and resume each other's cells.
"""

QUANT_SEMANTICS = 2  # 2: `hadamard` rotates residual streams offline where their RMSNorms fold (issue 31)
