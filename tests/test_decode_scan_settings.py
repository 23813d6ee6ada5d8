"""A scan's own decode defaults (``[structured_light.decode]``, docs/scan-format.md): used by the
decode stage under any setting given to it, recorded in its metrics, checked at the boundary."""

from __future__ import annotations

import tomllib

import pytest
import tomli_w

from facegeo.errors import InputError


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("decode_scan_settings") / "tiny"
    generate_scan(root, "tiny")
    return root


def _with_decode_table(root, table):
    path = root / "scan.toml"
    m = tomllib.loads(path.read_text())
    m["structured_light"]["decode"] = table
    path.write_text(tomli_w.dumps(m))
    from facegeo.capture.scan import load_scan

    return load_scan(root)


def test_scan_decode_table_sets_the_stage_defaults(tiny, tmp_path):
    from facegeo.pipeline.decode import decode_products, scan_decode_settings

    scan = _with_decode_table(tiny, {"rel_contrast": 0.05, "min_modulation": 0.2})
    assert scan_decode_settings(scan) == {"rel_contrast": 0.05, "min_modulation": 0.2}
    cam = scan.camera_names[:1]
    (tmp_path / "a").mkdir()
    m, used = decode_products(scan, tmp_path / "a", cameras=cam)
    assert used["rel_contrast"] == 0.05 and used["min_modulation"] == 0.2
    assert m["settings_from_scan"] == {"rel_contrast": 0.05, "min_modulation": 0.2}
    # a setting given to the stage wins and is not reported as the scan's
    (tmp_path / "b").mkdir()
    m, used = decode_products(scan, tmp_path / "b", cameras=cam, rel_contrast=0.1)
    assert used["rel_contrast"] == 0.1
    assert m["settings_from_scan"] == {"min_modulation": 0.2}


@pytest.mark.parametrize("table, match", [({"rel_contrst": 0.05}, "unknown"),
                                          ({"rel_contrast": -1.0}, "rel_contrast"),
                                          ({"rel_contrast": "low"}, "rel_contrast")])
def test_bad_scan_decode_table_is_a_clear_error(tiny, table, match, tmp_path):
    from facegeo.pipeline.decode import decode_products

    scan = _with_decode_table(tiny, table)
    with pytest.raises(InputError, match=match) as err:
        decode_products(scan, tmp_path, cameras=scan.camera_names[:1])
    assert "[structured_light.decode]" in str(err.value)
