"""The fit's random streams: one independent generator per use, all seeded from the config's seed.

Separate streams keep unrelated choices apart: how often previews are written or the guard looks
never moves what training samples, and a render without jitter draws nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class RandomStreams:
    sampling: np.random.Generator  # what each step looks at: stage-2 branch, pose, camera, part, patch
    jitter: np.random.Generator  # seeds of the ray-sample jitter of training renders
    backgrounds: torch.Generator  # random background colours behind training crops
    blocks: torch.Generator  # which grid block the regularisers look at

    @classmethod
    def from_seed(cls, seed: int) -> RandomStreams:
        sampling, jitter, backgrounds, blocks = np.random.SeedSequence(seed).spawn(4)
        return cls(
            np.random.default_rng(sampling),
            np.random.default_rng(jitter),
            torch.Generator().manual_seed(int(backgrounds.generate_state(1, np.uint64)[0] >> 1)),
            torch.Generator().manual_seed(int(blocks.generate_state(1, np.uint64)[0] >> 1)),
        )

    def background(self, device: torch.device) -> torch.Tensor:
        """A random (3,) background colour on ``device``."""
        return torch.rand(3, generator=self.backgrounds).to(device)

    def jitter_seed(self) -> int:
        return int(self.jitter.integers(1 << 30))

    def state(self) -> dict:
        """Everything needed to continue the streams: numpy states (JSON-able) and torch states (uint8 tensors)."""
        return {
            "sampling": self.sampling.bit_generator.state,
            "jitter": self.jitter.bit_generator.state,
            "backgrounds": self.backgrounds.get_state(),
            "blocks": self.blocks.get_state(),
        }

    def load_state(self, state: dict) -> None:
        self.sampling.bit_generator.state = state["sampling"]
        self.jitter.bit_generator.state = state["jitter"]
        self.backgrounds.set_state(state["backgrounds"])
        self.blocks.set_state(state["blocks"])
