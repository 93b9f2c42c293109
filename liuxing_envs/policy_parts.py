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
        convs = self.convolutions(channels, grid)
        self.net = nn.Sequential(
            convs,
            nn.Linear(_output_size(convs, (channels, grid, grid, grid)), features),
            nn.ReLU(),
        )

    @staticmethod
    def convolutions(channels: int, grid: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv3d(channels, 8, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv3d(8, 16, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )

    def forward(self, flat: torch.Tensor) -> torch.Tensor:
        grid = self.grid
        return self.net(flat.reshape(-1, self.channels, grid, grid, grid))


class HalvingMaxPool3d(nn.Module):
    """``nn.MaxPool3d(2)`` of cubes with even sides, as three pairwise maxima: the same
    numbers (NaN included), at about a third of the cost on a CPU, where torch's 3-D pooling
    kernel was the dearest layer of a gradient step."""

    def forward(self, cubes: torch.Tensor) -> torch.Tensor:
        batch, channels, depth, height, width = cubes.shape
        halves = cubes.reshape(batch, channels, depth, height, width // 2, 2)
        cubes = torch.maximum(halves[..., 0], halves[..., 1])
        halves = cubes.reshape(batch, channels, depth, height // 2, 2, width // 2)
        cubes = torch.maximum(halves[..., 0, :], halves[..., 1, :])
        halves = cubes.reshape(batch, channels, depth // 2, 2, height // 2, width // 2)
        return torch.maximum(halves[:, :, :, 0], halves[:, :, :, 1])


def average_pool(shape: tuple[int, ...], side: int) -> nn.Module:
    """``nn.AdaptiveAvgPool2d(side)`` of images of ``shape`` (C, H, W): as a plain
    ``nn.AvgPool2d`` where the windows tile the image and hold a power-of-two count of
    pixels (then both divide exactly, so the numbers are the same, and the plain one is
    cheaper), else the adaptive one itself."""
    height, width = shape[1], shape[2]
    rows, columns = height // side, width // side
    area = rows * columns
    if height == rows * side and width == columns * side and area & (area - 1) == 0:
        return nn.AvgPool2d((rows, columns))
    return nn.AdaptiveAvgPool2d(side)


class PooledImageEncoder(nn.Sequential):
    """The image averaged down to 16x16 pixels, one strided 3x3 convolution and a linear
    layer: about a fifteenth of :class:`ImageEncoder`'s cost per gradient step at 64x64."""

    SIDE = 16

    def __init__(self, shape: tuple[int, ...], features: int) -> None:
        channels = shape[0]
        side = min(self.SIDE, *shape[1:])
        if side < 3:
            raise ValueError(
                "the pooled image encoder needs images of at least 3x3 pixels, "
                f"got {shape[1]}x{shape[2]}"
            )
        convs = nn.Sequential(
            average_pool(shape, side),
            nn.Conv2d(channels, 16, kernel_size=3, stride=2),
            nn.ReLU(),
            nn.Flatten(),
        )
        super().__init__(convs, nn.Linear(_output_size(convs, shape), features), nn.ReLU())


class PooledOccupancyEncoder(OccupancyEncoder):
    """The occupancy cubes max-pooled to half their side (a cell is occupied when any of its
    eight is), one strided 3-D convolution and a linear layer."""

    @staticmethod
    def convolutions(channels: int, grid: int) -> nn.Sequential:
        if grid % 2:
            raise ValueError(f"the pooled occupancy encoder needs an even grid side, got {grid}")
        return nn.Sequential(
            HalvingMaxPool3d(),
            nn.Conv3d(channels, 8, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )


class PerceptionExtractor(BaseFeaturesExtractor):
    """Image CNNs, a 3-D occupancy CNN and pass-through vectors, concatenated (see module)."""

    image_encoder: type[nn.Module] = ImageEncoder
    map_encoder: type[OccupancyEncoder] = OccupancyEncoder

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
                encoders[key] = self.image_encoder(space.shape, image_features)
                total += image_features
            elif key == MAP_KEY:
                encoders[key] = self.map_encoder(
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


class PooledPerceptionExtractor(PerceptionExtractor):
    """:class:`PerceptionExtractor` on pooled inputs: depth images averaged to 16x16 pixels
    and occupancy cubes max-pooled to half their side before one convolution each, so that a
    gradient step costs a fraction (on one CPU thread, the learner was most of training)."""

    image_encoder = PooledImageEncoder
    map_encoder = PooledOccupancyEncoder


class NormalizedObservations(BaseFeaturesExtractor):
    """Another features extractor behind fixed observation statistics: what SB3's
    ``VecNormalize`` does outside the policy, done inside it, so that ``predict`` takes the
    env's raw observations and a saved model needs no second file.

    ``statistics`` maps each normalised observation key (None for a Box space) to its
    ``(mean, var)``; a key is scaled to ``clip((x - mean) / sqrt(var + epsilon), -clip, clip)``
    in float64 and then rounded to float32, as ``VecNormalize.normalize_obs`` does, so the
    extractor sees the same numbers bit for bit.
    """

    def __init__(
        self,
        observation_space: gym.Space,
        statistics: dict,
        clip: float,
        epsilon: float,
        extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        extractor_kwargs: dict | None = None,
    ) -> None:
        extractor = extractor_class(observation_space, **(extractor_kwargs or {}))
        super().__init__(observation_space, features_dim=extractor.features_dim)
        self.extractor = extractor
        self.clip = float(clip)
        self.keys = list(statistics)
        for index, key in enumerate(self.keys):
            mean, var = (np.asarray(value, dtype=np.float64) for value in statistics[key])
            self.register_buffer(f"mean_{index}", torch.from_numpy(mean.copy()))
            self.register_buffer(f"scale_{index}", torch.from_numpy(np.sqrt(var + epsilon)))

    def _normalized(self, value: torch.Tensor, index: int) -> torch.Tensor:
        mean, scale = getattr(self, f"mean_{index}"), getattr(self, f"scale_{index}")
        scaled = (value.double() - mean) / scale
        return torch.clamp(scaled, -self.clip, self.clip).float()

    def forward(self, observations):
        if self.keys == [None]:
            return self.extractor(self._normalized(observations, 0))
        observations = dict(observations)
        for index, key in enumerate(self.keys):
            observations[key] = self._normalized(observations[key], index)
        return self.extractor(observations)


def with_embedded_normalizer(model, normalizer):
    """``model`` (PPO or SAC) with ``normalizer``'s statistics (a ``VecNormalize``) moved into
    its policy as :class:`NormalizedObservations` in front of each features extractor; the
    weights are kept, the optimisers start afresh. Its ``predict`` on raw observations acts as
    ``model.predict`` did on normalised ones. Rewards are not touched (a policy never sees
    them)."""
    if not normalizer.norm_obs:
        return model
    if isinstance(normalizer.obs_rms, dict):
        statistics = {
            key: (normalizer.obs_rms[key].mean, normalizer.obs_rms[key].var)
            for key in normalizer.norm_obs_keys
        }
    else:
        statistics = {None: (normalizer.obs_rms.mean, normalizer.obs_rms.var)}
    policy = model.policy
    kwargs = dict(model.policy_kwargs)
    kwargs["features_extractor_class"] = NormalizedObservations
    kwargs["features_extractor_kwargs"] = {
        "statistics": statistics,
        "clip": float(normalizer.clip_obs),
        "epsilon": float(normalizer.epsilon),
        "extractor_class": policy.features_extractor_class,
        "extractor_kwargs": dict(policy.features_extractor_kwargs),
    }
    embedded = type(policy)(
        model.observation_space, model.action_space, model.lr_schedule, **kwargs
    ).to(model.device)
    weights = embedded.state_dict()
    for name, value in policy.state_dict().items():
        weights[name.replace("features_extractor.", "features_extractor.extractor.")] = value
    embedded.load_state_dict(weights)
    embedded.set_training_mode(False)
    model.policy = embedded
    model.policy_kwargs = kwargs
    if hasattr(model, "_create_aliases"):  # SAC's actor / critic / critic_target
        model._create_aliases()
    return model


#: Names a hyper-parameter file may give as ``policy_kwargs.features_extractor``.
FEATURES_EXTRACTORS = {
    "perception": PerceptionExtractor,
    "perception_pooled": PooledPerceptionExtractor,
    "combined": CombinedExtractor,
}
#: Names a hyper-parameter file may give as ``policy_kwargs.activation_fn``.
ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}
#: Names a hyper-parameter file may give as ``policy_kwargs.optimizer_class``.
OPTIMIZERS = {
    "adam": torch.optim.Adam,
    "adamw": torch.optim.AdamW,
    "rmsprop": torch.optim.RMSprop,
    "sgd": torch.optim.SGD,
}
