"""lab/wm-variants/wm_scale.py's pure parts: the worker split, the --variant syntax and the encoders the variants need.
(The script itself runs on a GPU machine; a CPU rehearsal is in its docstring.)"""

from __future__ import annotations

import argparse

import pytest


@pytest.fixture(scope="module")
def wm_scale(repo_script):
    return repo_script("lab/wm-variants/wm_scale.py")


def test_the_worker_split_sums_to_the_total_with_one_per_source_at_least(wm_scale):
    for total in range(1, 33):
        counts = wm_scale.split_workers(total)
        assert len(counts) == len(wm_scale.SOURCES) and min(counts) >= 1
        assert sum(counts) == max(total, len(wm_scale.SOURCES))
    assert wm_scale.split_workers(15) == [2, 2, 3, 8]  # the recipe's shares exactly


def test_variants_parse_like_a_shell_and_name_their_encoders(wm_scale):
    name, flags = wm_scale.variant("""dct=--action-conditioning adaln --encoder-kwargs '{"basis": "dct"}'""")
    assert name == "dct" and flags == ["--action-conditioning", "adaln", "--encoder-kwargs", '{"basis": "dct"}']
    assert wm_scale.encoder_setting(flags) == '{"basis": "dct"}'
    assert wm_scale.encoder_setting(["--encoder-kwargs={}", "--depth", "2"]) == "{}"
    assert wm_scale.variant("mini=") == ("mini", []) and wm_scale.encoder_setting([]) == "{}"
    spellings = ("{}", '{"basis": "random"}', '{"seed": 0, "basis": "random"}')  # one encoder, one feature cache
    assert len({wm_scale.features_of(x) for x in spellings}) == 1
    assert wm_scale.features_of('{"basis":"dct"}') != wm_scale.features_of("{}")
    with pytest.raises(argparse.ArgumentTypeError, match="is not JSON"):
        wm_scale.encoder_setting(["--encoder-kwargs", "{basis: dct}"])
    for bad in ("no-equals", "=--depth 2", "a/b=--depth 2"):
        with pytest.raises(argparse.ArgumentTypeError, match="NAME=FLAGS"):
            wm_scale.variant(bad)
