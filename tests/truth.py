"""Helpers that compare results with a simulated scenario's truth."""


def truth_scene(scenario, capture="visit0-a"):
    """Open3D raycasting scene of the posed body of a capture (for distances to the truth)."""
    from recon_engine.o3d import o3d

    mesh = o3d.t.io.read_triangle_mesh(str(scenario / "truth" / capture / "body.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    return scene
