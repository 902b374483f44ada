"""Conv1d whose weight gradient is one matrix product on the CPU when the weight is large.

oneDNN's convolution weight gradient on this generation of x86 CPUs is 4-12x slower than the
same arithmetic as a matrix product once the weight no longer fits the cache (measured at the
paper-sim U-Net's 1024-channel level, batch 128, length 4: 437 ms against 73 ms on one core),
and on sequences of two steps (the world model's lowest level), while its forward and input
gradient stay fast. :class:`Conv1d` keeps ``nn.Conv1d``'s parameters and state_dict (checkpoints
are interchangeable) and its forward; on the CPU, in float32, where :func:`matmul_pays` it computes

    grad_W[o, c, k] = sum_{b, t} grad_y[b, o, t] * x_pad[b, c, t + k]

as ``grad_y [O, B*T] @ im2col(x) [B*T, C*K]``, and the input gradient with torch's own kernel.
The results equal ``nn.Conv1d``'s within float rounding (tested). Stride 1, no dilation, one group,
batched input; the fast backward is not itself differentiable (no double backward: use
``weight_grad="onednn"`` for that).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

WEIGHT_GRAD_MODES = ("auto", "matmul", "onednn")


def matmul_pays(weight_numel: int, length: int) -> bool:
    """Where the matmul weight gradient made a conv's forward + backward faster on the 2-core EPYC
    development machine (32 MiB L3, fp32, 2 threads, batch 32 and 128, kernel 5): weights of 4 M+
    elements at every length (1024x1024x5: 1.4-3.7x, e.g. 351 -> 113 ms at batch 128, length 4), and
    weights of 256 K+ elements on sequences of at most 2 steps (512x512x5: 1.3-1.8x). Elsewhere oneDNN
    is as fast or faster (128 channels at length 4: the matmul 1.4-1.8x slower)."""
    return weight_numel >= 1 << 22 or (length <= 2 and weight_numel >= 1 << 18)


class _MatmulWeightGradConv1d(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, padding: int) -> Tensor:
        ctx.save_for_backward(x, weight)
        ctx.padding = padding
        ctx.has_bias = bias is not None
        return F.conv1d(x, weight, bias, padding=padding)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_y: Tensor):
        x, weight = ctx.saved_tensors
        pad = ctx.padding
        grad_x = grad_w = grad_b = None
        grad_y = grad_y.contiguous()
        if ctx.needs_input_grad[0]:
            grad_x = torch.ops.aten.convolution_backward(
                grad_y, x, weight, None, [1], [pad], [1], False, [0], 1, [True, False, False]
            )[0]
        if ctx.needs_input_grad[1]:
            out_ch, in_ch, k = weight.shape
            batch, _, length = grad_y.shape
            # im2col: [B, C, T + 2 pad] -> windows [B, C, T, K] -> rows (b, t), columns (c, k)
            cols = F.pad(x, (pad, pad)).unfold(2, k, 1).permute(0, 2, 1, 3).reshape(batch * length, in_ch * k)
            grad_w = (grad_y.permute(1, 0, 2).reshape(out_ch, batch * length) @ cols).view(out_ch, in_ch, k)
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = grad_y.sum((0, 2))
        return grad_x, grad_w, grad_b, None


class Conv1d(nn.Conv1d):
    """``nn.Conv1d`` (same parameters, state_dict and forward) whose CPU weight gradient is a matmul where
    that is faster: ``weight_grad`` "auto" (:func:`matmul_pays`), "matmul" (always) or "onednn" (never)."""

    def __init__(self, *args, weight_grad: str = "auto", **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if weight_grad not in WEIGHT_GRAD_MODES:
            raise ValueError(f"weight_grad must be one of {', '.join(WEIGHT_GRAD_MODES)}; got {weight_grad!r}")
        self.weight_grad = weight_grad

    def _matmul_grad(self, x: Tensor) -> bool:
        if self.weight_grad == "onednn" or (
            self.weight_grad == "auto" and not matmul_pays(self.weight.numel(), x.shape[-1])
        ):
            return False
        return (
            x.dim() == 3
            and self.weight.requires_grad
            and torch.is_grad_enabled()
            and x.device.type == "cpu"
            and x.dtype == torch.float32
            and self.weight.dtype == torch.float32
            and not torch.is_autocast_enabled("cpu")
            and self.stride == (1,)
            and self.dilation == (1,)
            and self.groups == 1
            and self.padding_mode == "zeros"
            and isinstance(self.padding, tuple)
        )

    def forward(self, x: Tensor) -> Tensor:
        if self._matmul_grad(x):
            return _MatmulWeightGradConv1d.apply(x, self.weight, self.bias, self.padding[0])
        return super().forward(x)
