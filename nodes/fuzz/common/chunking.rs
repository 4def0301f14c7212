//! Shared by the stream targets: cut the input into chunks whose sizes (1 to
//! 23 bytes) are drawn from the input itself, so the fuzzer explores chunking
//! as well as content. Kept outside `fuzz_targets/` so `ci-smoke.sh` does not
//! take it for a target.

pub fn chunks(bytes: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    let mut rest = bytes;
    let mut i = 0;
    while !rest.is_empty() {
        let size = 1 + usize::from(bytes[i % bytes.len()]) % 23;
        let (chunk, tail) = rest.split_at(size.min(rest.len()));
        out.push(chunk);
        rest = tail;
        i += 1;
    }
    out
}
