"""The ``cwfs-ros`` command line: :func:`main` and one module per command family.

* :mod:`.main`: the parser and the pair commands (``estimate``, ``pair-demo``);
* :mod:`.batch`, :mod:`.provenance`, :mod:`.pair_figure`, :mod:`.plotting`: results and figures;
* :mod:`.demo`: the closed-loop demo; :mod:`.replay`: offline replay of a bag;
* :mod:`.validate`: the paper's figures.
"""

from cwfs_ros.cli.main import main

__all__ = ["main"]
