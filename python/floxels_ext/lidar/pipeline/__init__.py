"""The parts of ``floxels run`` for one sequence that the engine (``lidar/dataset/``) assembles:
its checks (``run_args``), its poses and times (``run_inputs``), what each output was computed
from (``resume``), reading and preprocessing one frame, ahead of use (``frame_loader``; its
checks ``frame_checks``), writing the outputs (``frame_writer``; ``worker_processes``:
``--worker-kind process``), the stage times (``stages``) and the progress bars (``progress``).

Imports ``io`` and ``preprocess``, never ``dataset``, ``viz`` or ``lidar.run``."""
