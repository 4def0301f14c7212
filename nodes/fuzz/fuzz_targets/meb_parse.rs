//! Any bytes as one MEB frame: parsing never panics, the view and the value
//! agree, and whatever parses re-emits to a frame that parses to the same value.
#![no_main]

use libfuzzer_sys::fuzz_target;
use protocols::meb::{MEB_MAX_FRAME_LEN, MebFrame, MebRepr};

fuzz_target!(|data: &[u8]| {
    let parsed = MebRepr::parse(data);
    let view = MebFrame::new_checked(data);
    assert_eq!(parsed, view.map(|frame| MebRepr::from_frame(&frame)));
    if let Ok(repr) = parsed {
        let mut out = [0u8; MEB_MAX_FRAME_LEN];
        let len = repr.emit(&mut out).expect("a parsed frame emits");
        assert!(len <= data.len(), "canonical form is never longer");
        assert_eq!(MebRepr::parse(&out[..len]), Ok(repr));
        assert_eq!(
            repr.shape(),
            MebFrame::new_checked(data).map(|f| f.shape()).unwrap()
        );
    }
});
