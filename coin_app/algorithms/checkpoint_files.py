"""The file names inside a coin_app checkpoint (importable without Ray: sweep readers use them)."""

META_FILE = "coin_app.json"  # the algorithm, scenario, seed, overrides and env steps of the run
MANIFEST_FILE = "coin_app_manifest.json"  # every file's size and SHA-256, the config hash and the code version
