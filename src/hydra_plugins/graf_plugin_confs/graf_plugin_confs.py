"""A Hydra ``SearchPathPlugin``: appends each graf plugin's conf folder (:data:`graf.plugins.CONF_DIRS`, filled by
:func:`graf.plugins.add_conf` when graf imports its plugins) to the search path of every Hydra app in the process,
after graf's own configs: a plugin adds options (``model=<its method>``) and never replaces one of graf's."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

from graf.plugins import CONF_DIRS


class GrafPluginConfs(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        for folder in CONF_DIRS:
            search_path.append(provider="graf-plugin", path=f"file://{folder}")
