//! Consistent Overhead Byte Stuffing: removes every zero from a frame's body so that a single
//! `0x00` can delimit frames on the wire, at a cost of one byte per 254.
//!
//! Both directions are bounded loops over the input, with no panic path: a destination that is
//! too small, or an encoding that is malformed, is an error.

/// Why a COBS operation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CobsError {
    /// The destination buffer is too small.
    NoRoom,
    /// A zero byte inside an encoded frame, or a code that runs past the end.
    Malformed,
}

/// Largest encoded size of `len` body bytes (without the delimiter).
pub const fn max_encoded_len(len: usize) -> usize {
    len + len / 254 + 1
}

/// Encodes `src` into `dst`, returning the encoded length (no delimiter is written).
pub fn encode(src: &[u8], dst: &mut [u8]) -> Result<usize, CobsError> {
    let mut code_at = 0usize; // where the current block's code byte goes
    let mut out = 1usize;
    let mut code = 1u8;
    if dst.is_empty() {
        return Err(CobsError::NoRoom);
    }
    for &b in src {
        if b == 0 {
            *dst.get_mut(code_at).ok_or(CobsError::NoRoom)? = code;
            code_at = out;
            out += 1;
            code = 1;
        } else {
            *dst.get_mut(out).ok_or(CobsError::NoRoom)? = b;
            out += 1;
            code += 1;
            if code == 0xFF {
                *dst.get_mut(code_at).ok_or(CobsError::NoRoom)? = code;
                code_at = out;
                out += 1;
                code = 1;
            }
        }
    }
    *dst.get_mut(code_at).ok_or(CobsError::NoRoom)? = code;
    if out > dst.len() {
        return Err(CobsError::NoRoom);
    }
    Ok(out)
}

/// Decodes an encoded frame (without its delimiter) in place, returning the body's length.
pub fn decode_in_place(buf: &mut [u8]) -> Result<usize, CobsError> {
    decode_in_place_counting(buf, &mut 0)
}

/// [`decode_in_place`], adding the number of loop iterations it ran to `steps` (at most one
/// per byte of `buf`: the fuzz tests check the decoder's work per byte with it).
pub fn decode_in_place_counting(buf: &mut [u8], steps: &mut u32) -> Result<usize, CobsError> {
    let mut read = 0usize;
    let mut write = 0usize;
    while read < buf.len() {
        *steps = steps.wrapping_add(1);
        let code = buf[read];
        if code == 0 {
            return Err(CobsError::Malformed);
        }
        read += 1;
        let end = read + code as usize - 1;
        if end > buf.len() {
            return Err(CobsError::Malformed);
        }
        while read < end {
            *steps = steps.wrapping_add(1);
            let b = buf[read];
            if b == 0 {
                return Err(CobsError::Malformed);
            }
            buf[write] = b;
            write += 1;
            read += 1;
        }
        if code != 0xFF && read < buf.len() {
            buf[write] = 0;
            write += 1;
        }
    }
    Ok(write)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use std::vec;

    #[test]
    fn known_vectors() {
        let mut out = [0u8; 16];
        let n = encode(&[0x11, 0x22, 0x00, 0x33], &mut out).unwrap();
        assert_eq!(&out[..n], &[0x03, 0x11, 0x22, 0x02, 0x33]);
        let n = encode(&[0x00], &mut out).unwrap();
        assert_eq!(&out[..n], &[0x01, 0x01]);
        let n = encode(&[], &mut out).unwrap();
        assert_eq!(&out[..n], &[0x01]);
    }

    proptest! {
        #[test]
        fn encoding_has_no_zero_and_decodes_back(body in prop::collection::vec(any::<u8>(), 0..700)) {
            let mut enc = vec![0u8; max_encoded_len(body.len())];
            let n = encode(&body, &mut enc).unwrap();
            prop_assert!(!enc[..n].contains(&0));
            let m = decode_in_place(&mut enc[..n]).unwrap();
            prop_assert_eq!(&enc[..m], &body[..]);
        }

        #[test]
        fn decoding_random_bytes_never_panics(mut junk in prop::collection::vec(any::<u8>(), 0..600)) {
            let _ = decode_in_place(&mut junk);
        }
    }
}
