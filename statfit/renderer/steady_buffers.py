"""The buffers of :class:`statfit.renderer.steady.SteadyRenderer`: static shapes for a loop's renderer.

Each buffer (the z-buffer's rows and candidates, the covered pixels, the pixels near an outline and
the pixel pairs) is sized at its first need (× ``MARGIN``, plus ``FLOOR``: one host read), filled by
enumerations that read nothing back (``cumsum`` of flags, slots looked up or scattered), and checked
every ``CHECK_EVERY`` calls: the largest need since the last check is read once, and a buffer it
exceeded is sized afresh at the next call. The calls in between drop what does not fit.

CUDA's deterministic scatters (``index_add``, ``index_put`` with accumulation) sort their indices and
add each index's writes one after another: a slot that thousands of masked lanes write takes
milliseconds a call. On a GPU (``lookups``) the enumerations therefore look their slots up with
``searchsorted`` instead of scattering, and the renderer's masked lanes that must scatter write
nothing (a zero, no key) into distinct real slots (``_spread``). On a CPU the scatters are the faster.
"""
from __future__ import annotations

import math

import torch

MARGIN = 1.25       # buffer size / need at sizing
FLOOR = 256         # and at least this many slots more
CHECK_EVERY = 16    # calls between reads of the largest need (the only host reads in the steady state)
BUFFERS = ("rows", "candidates", "pixels", "edges", "pairs")


class SteadyBuffers:
    """Buffer sizes, cached index ranges and the needs' check of a renderer on ``device``."""

    def __init__(self, device: torch.device):
        self.device = device
        self.lookups = device.type != "cpu"
        self._sizes: dict[str, int] = {}
        self._aranges: dict = {}
        self._need: torch.Tensor | None = None
        self._calls = 0

    def _size(self, name: str, need: torch.Tensor) -> int:
        """The buffer size for ``name``; measured (one host read) only when not sized yet."""
        if name not in self._sizes:
            self._sizes[name] = int(math.ceil(int(need) * MARGIN)) + FLOOR
        return self._sizes[name]

    def _ones(self, size: int) -> torch.Tensor:
        if -size not in self._aranges:
            self._aranges[-size] = torch.ones(size, dtype=torch.long, device=self.device)
        return self._aranges[-size]

    def _arange(self, size: int) -> torch.Tensor:
        if size not in self._aranges:
            self._aranges[size] = torch.arange(size, dtype=torch.long, device=self.device)
        return self._aranges[size]

    def _spread(self, size: int, modulus: int) -> torch.Tensor:
        """0, 1, … modulo ``modulus`` (size,): distinct slots for masked lanes to write nothing into."""
        if ("spread", size, modulus) not in self._aranges:
            self._aranges["spread", size, modulus] = self._arange(size) % modulus
        return self._aranges["spread", size, modulus]

    def _check(self, need: torch.Tensor) -> None:
        """Keep the largest need (on the device, in place) and count the call (:meth:`replayed`),
        unless a CUDA graph is capturing it: then whoever replays it counts."""
        self._need = need.clone() if self._need is None else torch.maximum(self._need, need, out=self._need)
        if not (self.device.type == "cuda" and torch.cuda.is_current_stream_capturing()):
            self.replayed()

    def replayed(self) -> bool:
        """Count a call (or a replay); every ``CHECK_EVERY`` read whether the largest need since
        the last read exceeded a buffer (one host read) and forget those buffers' sizes: True if
        any was (the next call sizes them afresh, a host read: not while a graph captures it)."""
        self._calls += 1
        if self._calls % CHECK_EVERY or self._need is None:
            return False
        sizes = torch.tensor([self._sizes[name] for name in BUFFERS], device=self.device)
        over = (self._need > sizes).tolist()
        self._need.zero_()
        for name, too_small in zip(BUFFERS, over):
            if too_small:
                del self._sizes[name]
        return any(over)

    def _select(self, flags: torch.Tensor, name: str, slot_map: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The indices of the set ``flags`` (L,) bool, ascending, in a buffer of slots (past the
        last: L), the running count (L,) (its last entry: the need) and, with ``slot_map`` (or on a
        CPU, where it is made anyway), each lane's slot (L,) (unset lanes: the buffer's size). On a
        GPU each slot looks its lane up (``searchsorted`` in the running count): a scatter's many
        writes to one dump slot serialise under CUDA's deterministic algorithms. On a CPU the
        scatter is the faster."""
        running = torch.cumsum(flags, 0)
        slots = self._size(name, running[-1])
        slot = torch.where(flags, running - 1, slots).clamp_max_(slots) if slot_map or not self.lookups else None
        if self.lookups:
            if ("from 1", slots) not in self._aranges:
                self._aranges["from 1", slots] = torch.arange(1, slots + 1, dtype=torch.long, device=self.device)
            return torch.searchsorted(running, self._aranges["from 1", slots]), running, slot
        lanes = torch.full((slots + 1,), len(flags), dtype=torch.long, device=self.device)
        return lanes.scatter_(0, slot, self._arange(len(flags)))[:slots], running, slot

    def _owners(self, counts: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Enumerate (owner, index) pairs, 0 ≤ index < counts[owner], into a buffer of slots: owner
        (slots,) (len(counts): past the end) and index (slots,); and the need (0-d). The owner of a
        slot is the number of owners that end at or before it: on a GPU ``searchsorted``; on a CPU
        without its binary search, the owners whose first pair lies at or before the slot, less one
        (a scatter of start marks: on a GPU the owners without pairs would all mark one slot)."""
        ends = torch.cumsum(counts, 0)
        slots = self._size(name, ends[-1])
        starts = ends - counts
        if self.lookups:
            owner = torch.searchsorted(ends, self._arange(slots), right=True)
        else:
            marks = torch.zeros(slots + 1, dtype=torch.long, device=self.device)
            owner = marks.index_add_(0, starts.clamp_max(slots), self._ones(len(counts))).cumsum_(0)[:slots] - 1
            owner = torch.where(self._arange(slots) < ends[-1], owner, len(counts))
        padded = torch.nn.functional.pad(starts, (0, 1), value=0)
        return owner, self._arange(slots) - padded.index_select(0, owner), ends[-1]
