"""The `cadsplat` CLI, kiosk, services and deployment files."""
