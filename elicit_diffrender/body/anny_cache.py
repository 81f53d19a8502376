"""``python -m elicit_diffrender.body.anny_cache``: build Anny's one-time cache (used by setup)."""

from .anny_model import build_cache

if __name__ == "__main__":
    build_cache()
