"""The shipped policies (`.qtab` files with their `.json` records), installed as `qnav_policies`.

Data only: look a policy up with `firmware_py.shipped_policies.shipped_policy(NAME)`
or pass `policies:NAME` where a policy file is accepted.
"""
