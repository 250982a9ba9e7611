"""The engine of ``floxels run``: every run, one sequence or a dataset, here or on Ray, is tasks
through one pipeline. ``run`` sends INPUT to ``local`` (one sequence, or a dataset with one
progress bar; with ``--engines N``, on N engines sharing this machine's device: ``engines``,
``engine_process``) or ``ray_runner`` (long-lived workers, several per GPU); ``tasks`` finds a
dataset's sequences and cuts them into tasks; ``summary`` writes a sequence's summary, merged
over the tasks that ran it; ``worker`` runs tasks through the engine in a process;
``sequence`` opens a task (checks, resume, reader) and writes its summary; ``stream`` runs
the method over the tasks' chunks, which ``layout`` lays end to end in one index space
(``scan_views``: what the method sees of them).

Builds on ``pipeline`` (its checks, loader, writer, resume), ``preprocess`` and ``io``; nothing
below imports it."""
