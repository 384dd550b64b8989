"""YAML files the operator hands in (a map's YAML, a settings file) cost bounded time and memory,
whatever they hold: a few hundred bytes of aliases ("billion laughs") ran ``rlutf map import``
and ``rlutf config --settings`` for minutes and past 5 GB before they were counted (the commands
themselves: ``tests/service/cli/test_bad_input.py``)."""

from __future__ import annotations

import time

import pytest
from yaml_laughs import laughs

from service.yamlfile import MAX_VALUES, YamlTooLarge, load_yaml


def test_a_document_whose_aliases_repeat_billions_of_values_is_refused_at_once() -> None:
    t0 = time.process_time()
    with pytest.raises(YamlTooLarge, match="more than 100,000 values"):
        load_yaml(laughs())
    assert time.process_time() - t0 < 5.0  # counted up to the limit, not through the billions


def test_anchors_within_reason_load_as_yaml_does() -> None:
    text = "base: &b {epsilon: 0.004, spread: 0.3}\nlocalizer: *b\nlist: [1, 2, 3]\n"
    assert load_yaml(text) == {
        "base": {"epsilon": 0.004, "spread": 0.3},
        "localizer": {"epsilon": 0.004, "spread": 0.3},
        "list": [1, 2, 3],
    }
    assert load_yaml(laughs(levels=4)) is not None  # 9 ** 4 = 6,561 values: well under
    assert 9**5 < MAX_VALUES < 9**6
