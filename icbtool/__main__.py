from icbtool.cli import main

# guarded: a multiprocessing child started with "spawn" imports the parent's __main__ module
# (e.g. the frame process of `icbtool gui`) and must not run the command line again
if __name__ == "__main__":
    raise SystemExit(main())
