"""The jobs: the durable queue, the jobs as admins see them, the worker threads, the worker processes and
their pool, and the runner's threads and scratch folders that blocking work uses."""
