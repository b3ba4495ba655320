"""A visual policy with the shape of the neural policies participants submit: a ResNet-18
encoder of the camera's RGB-D frame and the arm's joint positions, an MLP head that predicts a
chunk of 8 actions. Random weights, seeded: the benchmark measures its cost, not its skill.

Runs on `POLICY_DEVICE` (`cuda` or `cpu`; default: cuda when torch sees a GPU).
"""

from __future__ import annotations

import itertools
import os

import numpy as np
import torch
from torch import nn

from manieval_sdk import Policy, TaskSpec, serve

CHUNK = 8


def block(cin: int, cout: int, stride: int) -> nn.Module:
    """A ResNet basic block's two 3x3 convolutions (no skip: the cost is the same)."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, 1, 1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class Network(nn.Module):
    def __init__(self, state_dim: int, action_dim: int) -> None:
        super().__init__()
        widths = (64, 64, 128, 256, 512)
        layers: list[nn.Module] = [nn.Conv2d(4, 64, 7, 2, 3, bias=False), nn.ReLU(inplace=True)]
        for cin, cout in itertools.pairwise(widths):
            layers += [block(cin, cout, 1 if cin == cout else 2), block(cout, cout, 1)]
        self.encoder = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.head = nn.Sequential(
            nn.Linear(512 + state_dim, 512), nn.ReLU(), nn.Linear(512, CHUNK * action_dim)
        )
        self.action_dim = action_dim

    def forward(self, image: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        features = torch.cat([self.encoder(image), state], dim=1)
        return torch.tanh(self.head(features)).view(-1, CHUNK, self.action_dim)


class VisualChunker(Policy):
    def setup(self, spec: TaskSpec) -> None:
        super().setup(spec)
        default = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(os.environ.get("POLICY_DEVICE", default))
        torch.manual_seed(0)
        qpos = spec.observation_space["agent"]["qpos"]["shape"][0]
        self.net = Network(qpos, spec.action_shape[0]).to(self.device).eval()

    @torch.inference_mode()
    def act(self, obs: dict) -> np.ndarray:
        camera = obs["sensor_data"]["base_camera"]
        rgb = torch.from_numpy(camera["rgb"]).to(self.device, non_blocking=True)
        depth = torch.from_numpy(camera["depth"].astype(np.float32)).to(self.device)
        image = torch.cat([rgb.float() / 255.0, depth / 1000.0], dim=-1).permute(2, 0, 1)
        state = torch.from_numpy(obs["agent"]["qpos"]).to(self.device).unsqueeze(0)
        chunk = self.net(image.unsqueeze(0), state)[0]
        return chunk.cpu().numpy()


if __name__ == "__main__":
    serve(VisualChunker())
