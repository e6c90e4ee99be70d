"""imugraph.graphs"""
