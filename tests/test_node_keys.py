"""NodeKeys: keyframe keys by robot block, a sequence of (robot_id, index) tuples."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.node_keys import NodeKeys


def test_node_keys_is_the_sequence_of_its_blocks() -> None:
    keys = NodeKeys([("a", np.array([0, 2, 5])), ("b", np.array([], dtype=np.int64)),
                     ("c", np.array([7, 8]))])  # fmt: skip
    listed = [("a", 0), ("a", 2), ("a", 5), ("c", 7), ("c", 8)]
    assert len(keys) == 5 and list(keys) == listed
    assert keys[3] == ("c", 7) and keys[-1] == ("c", 8) and keys[1:4] == listed[1:4]
    assert type(keys[0][1]) is int
    with pytest.raises(IndexError):
        keys[5]
    spans = [(rid, idx.tolist(), (s.start, s.stop)) for rid, idx, s in keys.spans()]
    assert spans == [("a", [0, 2, 5], (0, 3)), ("b", [], (3, 3)), ("c", [7, 8], (3, 5))]


def test_node_keys_of_a_list_groups_runs_of_one_robot() -> None:
    listed = [("a", 0), ("a", 1), ("b", 4), ("a", 2)]
    keys = NodeKeys.of(listed)
    assert [rid for rid, _ in keys.blocks] == ["a", "b", "a"] and list(keys) == listed
    assert NodeKeys.of(keys) is keys and len(NodeKeys.of([])) == 0
