"""imugraph.diagnose"""
