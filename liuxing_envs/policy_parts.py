"""Policy parts for SB3: a features extractor sized for this suite's observations.

They live in the package, not beside the training scripts, because a saved model names them
by import path: a model trained here loads wherever the package is installed. Importing this
module imports torch and SB3 (the ``train`` extra); ``import liuxing_envs`` does not.

SB3's default ``CombinedExtractor`` runs NatureCNN (built for 84x84 Atari frames; 1.7 M
weights after its 64x64 flatten) on images and flattens everything else, so the 4096-cell
occupancy map of ViewPlanning-v0 enters the MLP as 4096 unrelated inputs.
:class:`PerceptionExtractor` instead uses

- a small strided CNN per image key (depth/RGB, channel-first uint8, 64x64 by default),
- a 3-D CNN on the ``map`` key (a G x G x G occupancy cube, indexed [x, y, z]), with the
  ``free_space`` key, when the env has one (``observe_free_space=True``), as its second
  channel,
- the identity on every other (vector) key,

and concatenates the results. Hyper-parameter files name it as
``policy_kwargs: {features_extractor: perception}``; see :data:`FEATURES_EXTRACTORS`.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor
from torch import nn

DEFAULT_IMAGE_FEATURES = 128
DEFAULT_MAP_FEATURES = 128
MAP_KEY = "map"
#: Further G^3 cubes on the map's grid, stacked onto it as channels of its 3-D CNN.
MAP_CHANNEL_KEYS = ("free_space",)


def _output_size(module: nn.Module, shape: tuple[int, ...]) -> int:
    with torch.no_grad():
        return int(module(torch.zeros(1, *shape)).shape[1])


#: The smallest image side the three strided convolutions of ImageEncoder leave a pixel of.
MIN_IMAGE_SIDE = 19


class ImageEncoder(nn.Sequential):
    """Three strided 3x3/5x5 convolutions and a linear layer: about 0.15 M weights at 64x64."""

    def __init__(self, shape: tuple[int, ...], features: int) -> None:
        channels = shape[0]
        if min(shape[1:]) < MIN_IMAGE_SIDE:  # torch would say only "kernel size can't be ..."
            raise ValueError(
                f"the perception extractor's image CNN needs images of at least "
                f"{MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels, got {shape[1]}x{shape[2]}: raise "
                "the env's resolution"
            )
        convs = nn.Sequential(
            nn.Conv2d(channels, 16, kernel_size=5, stride=2),
            nn.ReLU(),
            nn.Conv2d(16, 32, kernel_size=3, stride=2),
            nn.ReLU(),
            nn.Conv2d(32, 32, kernel_size=3, stride=2),
            nn.ReLU(),
            nn.Flatten(),
        )
        super().__init__(convs, nn.Linear(_output_size(convs, shape), features), nn.ReLU())


class OccupancyEncoder(nn.Module):
    """A 3-D CNN over ``channels`` flat G^3 cubes (G a multiple of 4), concatenated."""

    def __init__(self, cells: int, features: int, channels: int = 1) -> None:
        super().__init__()
        grid = round(cells ** (1 / 3))
        if grid**3 != cells:
            raise ValueError(f"the {MAP_KEY!r} observation must hold G^3 cells, got {cells}")
        self.grid = grid
        self.channels = channels
        convs = nn.Sequential(
            nn.Conv3d(channels, 8, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv3d(8, 16, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        self.net = nn.Sequential(
            convs,
            nn.Linear(_output_size(convs, (channels, grid, grid, grid)), features),
            nn.ReLU(),
        )

    def forward(self, flat: torch.Tensor) -> torch.Tensor:
        grid = self.grid
        return self.net(flat.reshape(-1, self.channels, grid, grid, grid))


class PerceptionExtractor(BaseFeaturesExtractor):
    """Image CNNs, a 3-D occupancy CNN and pass-through vectors, concatenated (see module)."""

    def __init__(
        self,
        observation_space: gym.spaces.Dict,
        image_features: int = DEFAULT_IMAGE_FEATURES,
        map_features: int = DEFAULT_MAP_FEATURES,
        normalized_image: bool = False,
    ) -> None:
        encoders: dict[str, nn.Module] = {}
        total = 0
        spaces = observation_space.spaces
        map_channels = [key for key in MAP_CHANNEL_KEYS if key in spaces]
        if map_channels and MAP_KEY not in spaces:
            raise ValueError(f"{map_channels} are channels of the missing {MAP_KEY!r} key")
        for key in map_channels:
            if spaces[key].shape != spaces[MAP_KEY].shape:
                raise ValueError(
                    f"{key!r} must have the {MAP_KEY!r} key's shape {spaces[MAP_KEY].shape}, "
                    f"got {spaces[key].shape}"
                )
        for key, space in spaces.items():
            if key in MAP_CHANNEL_KEYS:
                continue
            if is_image_space(space, normalized_image=normalized_image):
                encoders[key] = ImageEncoder(space.shape, image_features)
                total += image_features
            elif key == MAP_KEY:
                encoders[key] = OccupancyEncoder(
                    int(np.prod(space.shape)), map_features, channels=1 + len(map_channels)
                )
                total += map_features
            else:
                encoders[key] = nn.Flatten()
                total += int(np.prod(space.shape))
        super().__init__(observation_space, features_dim=total)
        self.encoders = nn.ModuleDict(encoders)
        self.map_channels = map_channels

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        features = []
        for key, encoder in self.encoders.items():
            value = observations[key]
            if key == MAP_KEY and self.map_channels:
                value = torch.cat([value, *(observations[k] for k in self.map_channels)], 1)
            features.append(encoder(value))
        return torch.cat(features, 1)


#: Names a hyper-parameter file may give as ``policy_kwargs.features_extractor``.
FEATURES_EXTRACTORS = {"perception": PerceptionExtractor, "combined": CombinedExtractor}
#: Names a hyper-parameter file may give as ``policy_kwargs.activation_fn``.
ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}
#: Names a hyper-parameter file may give as ``policy_kwargs.optimizer_class``.
OPTIMIZERS = {
    "adam": torch.optim.Adam,
    "adamw": torch.optim.AdamW,
    "rmsprop": torch.optim.RMSprop,
    "sgd": torch.optim.SGD,
}
