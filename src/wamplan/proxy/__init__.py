"""The planning proxy (``wamplan serve``): an ``/act`` endpoint between a robot and a WAM server that plans each
chunk the WAM proposes in a world model and answers in the WAM's own format. ``config.py`` holds its settings,
``upstream.py`` the WAM behind it, ``sessions.py`` one robot's episode, ``app.py`` the request handling and the
HTTP endpoint, ``build.py`` the start-up (loading, the fit check)."""
