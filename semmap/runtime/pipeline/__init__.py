"""The per-frame pipeline: the stage objects each service wraps (stages) and the in-process driver that runs the
same stages in one process in lockstep order, derived from the dataflow table (inprocess)."""
