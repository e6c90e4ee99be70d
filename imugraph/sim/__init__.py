"""imugraph.sim"""
