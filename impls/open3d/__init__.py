"""Open3D's RaycastingScene as an engine backend: :mod:`impls.open3d.backend`."""
