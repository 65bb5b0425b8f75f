"""One router per resource; :func:`server.main.create_app` includes them."""
