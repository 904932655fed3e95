"""Model making: colliders from meshes. Reading mesh files and placing them (:mod:`.mesh_files`,
:mod:`.placement`), baking (:mod:`.bake`), training neural colliders (:mod:`.training`), the
point sets around a surface (:mod:`.sampling`) and measuring a collider against its mesh
(:mod:`.evaluation`). Needs the ``train`` extra (trimesh, scikit-image, tqdm)."""
