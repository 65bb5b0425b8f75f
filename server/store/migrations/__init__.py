"""The schema's versions (Alembic): ``versions/`` holds one revision a change, ``0001`` the base. The service
runs them through :mod:`kitti_eval_server.store.schema`; ``env.py`` is Alembic's entry, given the connection."""
