//! `sdsem` command line: parse, initialise, run, turn the result into an exit code.

fn main() {
    println!("sdsem {}", env!("CARGO_PKG_VERSION"));
}
