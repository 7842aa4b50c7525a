"""Learned models with weights shipped inside the package (see :mod:`cm3d.models.pointnet2`)."""
