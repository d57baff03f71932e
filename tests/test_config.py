"""The typed config: sections, overrides, and settings that moved section."""

import pytest

from ti_fusion.config import Config, load_config
from ti_fusion.errors import InputError


def test_maps_section_and_moved_keys(tmp_path):
    cfg = load_config(None, ["maps.depth_smooth_radius=3", "maps.normal_max_depth_jump=0.07"])
    assert cfg.maps.depth_smooth_radius == 3 and cfg.maps.normal_max_depth_jump == 0.07
    # the frame-map settings used to be in [icp]: the old names set the new ones
    path = tmp_path / "old.toml"
    path.write_text("[icp]\ndepth_smooth_radius = 2\npyramid_depth_sigma = 0.02\ndist_threshold = 0.05\n")
    cfg = load_config(path)
    assert (cfg.maps.depth_smooth_radius, cfg.maps.pyramid_depth_sigma, cfg.icp.dist_threshold) == (2, 0.02, 0.05)
    assert not hasattr(cfg.icp, "depth_smooth_radius")
    assert "maps" in Config().to_dict()


def test_unknown_setting_is_one_clear_line():
    with pytest.raises(InputError, match="unknown setting 'depth_smooth'"):
        load_config(None, ["maps.depth_smooth=2"])


def test_non_positive_range_check_is_refused(cpu):
    from ti_fusion.config import MapsConfig
    from ti_fusion.kernels.maps import FrameMaps

    with pytest.raises(InputError, match="maps.pyramid_depth_sigma"):
        FrameMaps(MapsConfig(pyramid_depth_sigma=0.0), 8, 8, levels=1)
