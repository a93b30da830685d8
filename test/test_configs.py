"""Tests of gcn_match_ros.configs: JsonConfig to/from plain JSON dicts for every settings class."""
import dataclasses
import json

import pytest

from gcn_match_ros.configs import JsonConfig
from gcn_match_ros.edges.candidates import EdgeConfig
from gcn_match_ros.graph import GraphConfig
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.model import GCNConfig
from gcn_match_ros.node_features import FeatureConfig

EXAMPLES = [
    GraphConfig(),
    GraphConfig(k=1, mutual=True, ratio=0.8, binary=True, rescale="none", normalization="rootsift"),
    FeatureConfig(),
    FeatureConfig(descriptor=False, normalization="rootsift", scale=False),
    EdgeConfig(),
    EdgeConfig(k=6, geometry=False, guided=False, guide_px=2.5, ratio=0.7, normalization="l2"),
    GCNConfig(),
    GCNConfig(in_dim=20, widths=(16, 16, 24), out_dim=8, groups=4, skip_layers=(3, 1), norm_layers=1,
              edge_features=14, edge_hidden=8, edge_k=3),
    TrainConfig(),
    TrainConfig(steps=7, grad_clip=1.5, graph=GraphConfig(k=2, ratio=0.9), features=FeatureConfig(position=False)),
]


def through_json(config):
    return json.loads(json.dumps(config.to_dict()))


@pytest.mark.parametrize("config", EXAMPLES, ids=lambda c: type(c).__name__)
def test_round_trip_through_json(config):
    assert isinstance(config, JsonConfig)
    d = through_json(config)
    assert d == config.to_dict()  # plain JSON values already
    assert set(d) == {f.name for f in dataclasses.fields(config)}
    back = type(config).from_dict(d)
    assert back == config and type(back) is type(config)


def test_tuples_become_lists_and_back():
    config = GCNConfig(widths=(16, 16, 24, 24), out_dim=12, groups=4, skip_layers=(2, 4))
    d = config.to_dict()
    assert d["widths"] == [16, 16, 24, 24] and d["skip_layers"] == [2, 4]
    back = GCNConfig.from_dict(through_json(config))
    assert back.widths == (16, 16, 24, 24) and back.skip_layers == (2, 4)


def test_nested_settings_become_nested_dicts_and_back():
    config = TrainConfig(graph=GraphConfig(k=2, mutual=True), features=FeatureConfig(orientation=False))
    d = through_json(config)
    assert d["graph"] == GraphConfig(k=2, mutual=True).to_dict()
    assert d["features"]["orientation"] is False
    back = TrainConfig.from_dict(d)
    assert isinstance(back.graph, GraphConfig) and isinstance(back.features, FeatureConfig)
    assert back.graph.k == 2 and back.graph.mutual and not back.features.orientation
    # a partial dict: missing keys take their defaults, nested ones too
    partial = TrainConfig.from_dict({"steps": 3, "graph": {"k": 5}})
    assert partial == TrainConfig(steps=3, graph=GraphConfig(k=5))


@pytest.mark.parametrize("cls", [GraphConfig, FeatureConfig, EdgeConfig, GCNConfig, TrainConfig])
def test_unknown_keys_are_refused_naming_the_class(cls):
    d = cls().to_dict()
    d["bogus"] = 1
    d["also_bogus"] = 2
    with pytest.raises(ValueError, match=rf"^{cls.__name__}: unknown keys \['also_bogus', 'bogus'\]"):
        cls.from_dict(d)


def test_unknown_keys_of_nested_settings_are_refused():
    with pytest.raises(ValueError, match="GraphConfig: unknown keys"):
        TrainConfig.from_dict({"graph": {"k": 2, "kk": 3}})


@pytest.mark.parametrize("cls, d, message", [
    (GraphConfig, {"k": 0}, "GraphConfig.k must be >= 1"),
    (GraphConfig, {"rescale": "log"}, "GraphConfig.rescale"),
    (FeatureConfig, {"normalization": "l3"}, "FeatureConfig.normalization"),
    (EdgeConfig, {"normalization": "l3"}, "EdgeConfig.normalization"),
    (GCNConfig, {"widths": [16, 18, 16], "groups": 4, "skip_layers": [3]},
     r"widths \[18\] are not divisible by groups=4"),
    (GCNConfig, {"norm": "batch"}, "GCNConfig.norm"),
    (TrainConfig, {"steps": 0}, "TrainConfig.steps must be >= 1"),
    (TrainConfig, {"features": {"normalization": "l3"}}, "FeatureConfig.normalization"),
])
def test_invalid_values_are_still_validated(cls, d, message):
    with pytest.raises(ValueError, match=message):
        cls.from_dict(d)
