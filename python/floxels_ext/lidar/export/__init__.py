"""Run outputs in the formats other tools read: ``floxels export`` (``command.py``).

``run_frames.py`` reads a ``floxels run`` OUT_DIR for every format (its sequences, each frame's
metadata, the flow turned into "where the point is at the next frame, in that frame's
coordinates"); ``av2_submission.py`` writes the Argoverse 2 scene flow challenge's files and zip;
``opensceneflow.py`` writes pseudo-labels as OpenSceneFlow's trainers read them (``.h5``). Uses
``io/`` only (beside ``viz/`` in the lidar package's import order)."""
