"""imugraph.body"""
