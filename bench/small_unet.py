"""A small UNet (three levels, 32-64-128 channels): the model step `bench.training_reader` feeds.

Sized like the event-to-image networks a 4D trainer runs per window (E2VID-like, without the
recurrence): at 1280x720 it is fast enough on a GPU that a slow loader shows.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.ReLU(inplace=True),
    )


class SmallUNet(nn.Module):
    """in_ch -> 1 channel, same size (height and width multiples of 4)."""

    def __init__(self, in_ch: int, base: int = 32) -> None:
        super().__init__()
        self.enc1, self.enc2, self.mid = (
            _block(in_ch, base),
            _block(base, 2 * base),
            _block(2 * base, 4 * base),
        )
        self.up2, self.dec2 = nn.ConvTranspose2d(4 * base, 2 * base, 2, stride=2), _block(4 * base, 2 * base)
        self.up1, self.dec1 = nn.ConvTranspose2d(2 * base, base, 2, stride=2), _block(2 * base, base)
        self.head = nn.Conv2d(base, 1, 1)
        self.pool = nn.MaxPool2d(2)

    def forward(self, x: torch.Tensor) -> Any:
        e1 = self.enc1(x)
        e2 = self.enc2(self.pool(e1))
        m = self.mid(self.pool(e2))
        d2 = self.dec2(torch.cat([self.up2(m), e2], dim=1))
        d1 = self.dec1(torch.cat([self.up1(d2), e1], dim=1))
        return self.head(d1)


class ModelStep:
    """One training step (forward, L1 loss, backward, Adam) of a SmallUNet on a batch; bf16
    autocast on CUDA, as a trainer would run it."""

    def __init__(self, in_ch: int, device: torch.device) -> None:
        self.device = device
        self.model = SmallUNet(in_ch).to(device).to(memory_format=torch.channels_last)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=1e-4)

    def __call__(self, x: torch.Tensor) -> None:
        if x.dim() == 3:
            x = x.unsqueeze(1)
        x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.device.type == "cuda"):
            out = self.model(x)
            loss = (out.float() - x[:, :1]).abs().mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
