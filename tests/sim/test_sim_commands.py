"""The simulator's commands without tracing: what they refuse, in one line."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from graf.app.config import CONF_DIR
from graf.data.spectrum_set import DataFormatError
from graf.errors import is_user_error
from graf.sim.show import show


def test_show_scenes_without_a_dataset_says_how_to_make_it(tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "show_scenes", [f"data_root={tmp_path}", "scenes=[small_room]", f"paths.output_dir={tmp_path / 'out'}"]
        )
    GlobalHydra.instance().clear()
    with pytest.raises(DataFormatError, match="small_room/2.4ghz.h5: no dataset; make it with graf-simulate") as err:
        show(cfg)
    assert is_user_error(err.value)  # one line and exit 2, not a traceback
