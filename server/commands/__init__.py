"""The service's commands of ``kitti-eval``: ``serve``, ``worker`` and ``admin``, one module each (its
``add_parser(sub)`` beside its ``run``)."""
