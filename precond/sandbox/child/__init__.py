"""The fork server and the children that run untrusted code (stdlib only).

The worker starts ``server`` as ``python -I -S`` with an empty environment; every module here is loaded
by that interpreter before any untrusted byte runs, and none of them imports the parent-side ``sandbox``
modules. The boundary itself is ``boundary``: read it on its own.
"""
