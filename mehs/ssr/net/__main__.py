"""``python -m mehs.ssr.net``: the zoo's parameter counts beside the published ones."""

from mehs.ssr.net.zoo import print_parameter_table

print_parameter_table()
