#!/usr/bin/env bash
# Sourced first by the figure scripts (and make_sample_bag.sh), before set-up: their arguments and settings checked
# before any work. A fresh-clone walk found `--help` or a typo running the whole job (set-up, renders, benches written
# over earlier results; make_sample_bag.sh rewrote the shipped bag), and a mistyped setting noticed only after minutes
# of work, or never (a selector naming nothing ran nothing and exited 0).

# script_args SCRIPT [ARGS...]: -h/--help prints SCRIPT's header comment and exits 0; any other argument is refused
# (exit 2): the figure scripts take none (their settings are environment variables, named in the header).
script_args() {
    local script=$1 name
    name="$(basename "$script")"
    shift
    case "${1:-}" in
        "") return 0 ;;
        -h | --help)
            awk 'NR == 1 { next } /^#/ { sub(/^# ?/, ""); print; next } { exit }' "$script"
            exit 0 ;;
        *)
            printf '%s: unknown argument(s): %s (see %s --help; its settings are environment variables)\n' \
                "$name" "$*" "$name" >&2
            exit 2 ;;
    esac
}

# require_int NAME MIN: the setting NAME (an environment variable, already defaulted by the script) is an integer >= MIN.
require_int() {
    local name=$1 min=$2 value
    value="${!1-}"
    if ! [[ "$value" =~ ^[0-9]+$ ]] || [ "$value" -lt "$min" ]; then
        printf '%s=%s: must be a whole number >= %s\n' "$name" "$value" "$min" >&2
        exit 2
    fi
}

# require_words NAME KNOWN...: every word of the setting NAME is one of KNOWN (a selector of rows, benches, parts).
require_words() {
    local name=$1 word
    shift
    for word in ${!name-}; do
        [[ " $* " == *" $word "* ]] || { printf "%s: unknown name '%s' (one of: %s)\n" "$name" "$word" "$*" >&2; exit 2; }
    done
}

# require_replica REPO: the Replica office0 sample the office0 figures read ($ROIGSF_SHARED_DATA, else
# REPO/../shared/data); sets DATA to its folder.
require_replica() {
    DATA="${ROIGSF_SHARED_DATA:-$1/../shared/data}/replica_office0"
    if [ ! -f "$DATA/office0_mesh.ply" ]; then
        printf 'Replica office0 sample not found at %s (it is not in the repository: put it in ../shared/data beside the repo, or set ROIGSF_SHARED_DATA to the folder holding replica_office0)\n' "$DATA" >&2
        exit 2
    fi
}
