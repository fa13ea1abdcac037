"""When a member's flow has stopped: the footprint rule (SolverConfig.stop_quiet_time), tested at the host
checks of torchslide.solver.simulate.

A member ends once, over the last ``stop_quiet_time`` seconds, no cell was newly reached (h >
arrival_threshold) and the thickness changed by less than ``stop_quiet_change`` of the volume (sum |dh| /
sum h), while its kinetic energy is below ``stop_quiet_ke`` of its peak: its footprint and its deposit are
then what a longer run would give, up to the creep of thin layers that Voellmy friction never holds on
slopes steeper than atan(mu).
"""
from __future__ import annotations

import torch
from torch import Tensor

from .config import SolverConfig


class QuietWatch:
    """The footprint rule's state for the working members: each one's thickness (B, ny, nx) at its last
    reference time (B,) s, and whether its thickness changed by less than stop_quiet_change of its volume
    over its last window."""

    def __init__(self, cfg: SolverConfig, h: Tensor):
        self.window, self.ke, self.change = cfg.stop_quiet_time, cfg.stop_quiet_ke, cfg.stop_quiet_change
        self.on = self.window > 0
        B = h.shape[0]
        self.ref_h = torch.zeros_like(h) if self.on else None
        self.ref_t = torch.zeros(B, dtype=h.dtype, device=h.device)
        self.h_quiet = torch.zeros(B, dtype=torch.bool, device=h.device)

    def quiet(self, work: dict, sub: dict, box) -> Tensor:
        """(B,) bool: the working members whose flow has stopped (module doc). ``work``: the per-member
        scalars (t, ke, ke_peak); ``sub``: the state on ``box`` (a crop.Box), which holds every wet cell."""
        if not self.on:
            return torch.zeros_like(work["active"])
        t = work["t"]
        h = sub["h"]
        ref = self.ref_h[:, box.r0:box.r1, box.c0:box.c1]
        due = (t - self.ref_t) >= self.window
        if bool(due.any()):
            moved = (h - ref).abs().sum(dim=(1, 2))
            self.h_quiet = torch.where(due, moved < self.change * h.sum(dim=(1, 2)), self.h_quiet)
            ref.copy_(torch.where(due.view(-1, 1, 1), h, ref))
            self.ref_t = torch.where(due, t, self.ref_t)
        a = sub["arrival"]
        last = torch.where(torch.isinf(a), torch.zeros_like(a), a).amax(dim=(1, 2))
        calm = work["ke"] < self.ke * work["ke_peak"]
        return calm & (t - last >= self.window) & self.h_quiet

    def keep(self, act: Tensor) -> None:
        """Drop the members that left the working batch (``act``: (B,) bool, those that stay)."""
        if self.on:
            self.ref_h, self.ref_t, self.h_quiet = self.ref_h[act], self.ref_t[act], self.h_quiet[act]
