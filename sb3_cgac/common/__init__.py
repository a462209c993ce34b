"""
Infrastructure that CGAC's modules share and that is not the algorithm itself (as SB3 keeps ``common/`` apart from
its algorithms): CUDA-graph replay of the updates (``cuda_graphs``), data-parallel training under torchrun
(``distributed``), the updates' statistics and checks (``diagnostics``), row operations on Box and Dict observations
(``obs_rows``) and the loading of models saved by earlier releases (``compat``).
"""
