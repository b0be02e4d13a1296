"""Studies of the reference controllers that write figures and tables: ``python -m studies.<name>``.

Not part of the installed library; they run from a checkout of the repository.
"""
