from diffuser_lab.cli.main import main

main()
