"""What uses ``floxels run``'s outputs: pictures (``show`` = ``floxels show``, ``flow_plot``:
matplotlib bird's-eye views, ``bev_png``: images without matplotlib) and densified clouds
(``accumulate`` = ``floxels accumulate``). Imports ``io`` only (the outputs, the readers)."""
