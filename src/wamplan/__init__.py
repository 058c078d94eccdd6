"""wamplan: world-model feedback planning for world action models."""
__version__ = "0.1.0"
