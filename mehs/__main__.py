from mehs.cli import console

console()
