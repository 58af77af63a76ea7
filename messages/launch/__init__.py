"""Process supervision of one run (what ``launch.py`` drives): node specs and processes,
the launch service with its authenticating hub, and a progress observer."""
