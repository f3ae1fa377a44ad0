"""Real-kernel quantization methods for `quantize_`: packed weights and integer/FP8 matrix products,
one module per family: `packed` (the packed-linear base classes, per-token input rows and the
layer swap every method shares), `bnb` (bitsandbytes), `int4` (int4 weight-only, AWQ), `int8` (int8 W8A8,
SmoothQuant), `fp8` (`torch._scaled_mm`) and `scaled_gemm` (the Triton GEMMs of int8, small-row FP8 and int4 on
CUDA, with tiles for pi0.5's few-row products).

Registered by name in `quant.methods` (each module imported when a cell first uses one of its methods):

    nf4          bitsandbytes 4-bit NormalFloat, blocks of 64, bf16 compute   (preset W4)
    int8         bitsandbytes LLM.int8(): int8 weights, fp16 outlier columns  (preset W8)
    int4wo       int4 weight-only, asymmetric groups                        (preset W4[G<g>])
                 (Triton W4A16 GEMM on CUDA, tinygemm `_weight_int4pack_mm_for_cpu` on the CPU;
                 AWQ's INT4 GEMM format without AWQ's scale search)
    awq          activation-aware weight quantization (`quant.awq` scale search on calibration
                 rows): W4 on CUDA as int4wo with the scales, fake-quantized elsewhere (W<b>[G<g>])
    smoothquant  W8A8 int8: per-channel weights, dynamic per-token activations, int32 products,
                 with SmoothQuant's per-channel migration vector (from calibration statistics,
                 required) folded into the weights                                           (W8A8)
    int8_dynamic W8A8 int8: the same kernel without smoothing (the int8 counterpart of fp8)  (W8A8)
    fp8          W8A8 FP8 e4m3: per-channel weights, dynamic per-token activations,
                 `torch._scaled_mm` with row-wise scales (the H100's native format)          (W8A8)
    fp8_tensor   the same with one scale per weight tensor and one per activation tensor (W8A8)
    fp8_static   FP8 with one weight scale and one static activation scale per layer, from the
                 calibration statistics' input absmax (as FP8 inference stacks serve)      (W8A8)

Each selected `nn.Linear` is replaced in its parent by a module holding the packed weight (the
bf16 weight is freed), and gets a counting pre-hook that changes nothing, so `unfired()` proves
that the kernel ran; the header's `quant_report.weight_memory` records the replaced layers' bytes as
released and as packed. bitsandbytes is an optional extra (`pip install vlaquantbench[kernels]`);
int4wo, smoothquant, int8_dynamic and fp8 need only PyTorch (fp8 needs a CUDA GPU and refuses any
other device by name before it changes a weight, since row-wise `torch._scaled_mm` runs on CUDA
GPUs of compute capability 8.9+ only; the int8 and int4 products also run on the CPU).

In pi0.5's captured sampler, `fp8` and `int8_dynamic` layers that read one input run as one product
on a merged weight (`packed.PerTokenLinear.merged`), their input cast to e4m3 or int8 rows by the op that
produces it (`input_cast`, `quant.grid.PerTokenCast`; `models.pi05.fast.linear_groups`); `int4wo`
layers run one by one as modules (bf16 inputs: nothing to cast). Numerics (W8A8
and W4A16 alike): scales FP32; everything between the products as in a BF16 cell (norms, softmax,
residuals, the float32 SigLIP tower's arithmetic), output in the layer's dtype (bf16, or float32
for the SigLIP tower and projector). FP8: FP32 accumulation in the tensor cores (fast accumulation
on Hopper) with the scales applied by `torch._scaled_mm`; products of at most `fp8.TRITON_MAX_ROWS` rows
run on `scaled_gemm` instead (FP32 accumulation, the scales in its epilogue). INT8: exact int32
accumulation, then (sum * s_x) * s_w in FP32 rounded once to the output dtype, in `scaled_gemm`'s
epilogue on CUDA (`dequantize_int32` on the CPU: the same arithmetic). INT4: bf16 activations, the
weights dequantized to bf16 inside the GEMM, FP32 accumulation, output bf16 (the float32 SigLIP
layers take and give bf16 here, their only change besides the weights).
"""
