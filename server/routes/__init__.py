"""One router per resource; :func:`kitti_eval_server.main.create_app` includes them."""
