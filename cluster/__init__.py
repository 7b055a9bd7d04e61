"""Running coin_app on a Ray cluster: the job client (``jobs.py``), launcher and KubeRay configs, the image."""
