//! Two modules on one MEB line, for a supervisor that polls both: the
//! master's TCP connection carries every request, and each goes to the
//! `twin serve` whose slave id it names, its reply back, as an RS-485 line
//! with two modules answers. A request to an id nobody has is not
//! answered, as on the line.

use protocols::meb::{MebDecoder, MebRepr};
use protocols::time::SimTime;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::Duration;

/// The line's address for the master (`tcp://127.0.0.1:PORT`); `slaves`
/// maps each id to its module's MEB link (`tcp://…`).
pub fn meb_bus(slaves: &[(u8, &str)]) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").expect("the bus listens");
    let addr = listener.local_addr().unwrap();
    let slaves: BTreeMap<u8, String> = slaves
        .iter()
        .map(|(id, url)| (*id, crate::common::host_port(url).to_string()))
        .collect();
    std::thread::spawn(move || {
        // The master may connect again after a failure.
        for master in listener.incoming().flatten() {
            carry(master, &slaves);
        }
    });
    format!("tcp://{addr}")
}

fn carry(mut master: TcpStream, slaves: &BTreeMap<u8, String>) {
    let mut open: BTreeMap<u8, (TcpStream, MebDecoder)> = BTreeMap::new();
    let mut decoder = MebDecoder::new();
    let mut buf = [0u8; 512];
    loop {
        let Ok(got) = master.read(&mut buf) else {
            return;
        };
        if got == 0 {
            return;
        }
        let mut rest = &buf[..got];
        while !rest.is_empty() {
            let (used, event) = decoder.push(SimTime::ZERO, rest);
            rest = &rest[used..];
            let Some(Ok(frame)) = event else { continue };
            let request = MebRepr::from_frame(&frame);
            let Some(url) = slaves.get(&request.id) else {
                continue;
            };
            let (slave, answers) = match open.entry(request.id) {
                std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
                std::collections::btree_map::Entry::Vacant(e) => {
                    let Ok(stream) = TcpStream::connect(url) else {
                        continue;
                    };
                    let _ = stream.set_read_timeout(Some(Duration::from_millis(300)));
                    e.insert((stream, MebDecoder::new()))
                }
            };
            if let Some(reply) = exchange(slave, answers, &request)
                && master.write_all(&reply).is_err()
            {
                return;
            }
        }
    }
}

/// The request to one module and its reply, re-emitted; `None` without one.
fn exchange(slave: &mut TcpStream, decoder: &mut MebDecoder, request: &MebRepr) -> Option<Vec<u8>> {
    let mut out = [0u8; 512];
    let n = request.emit(&mut out).ok()?;
    slave.write_all(&out[..n]).ok()?;
    let mut buf = [0u8; 512];
    loop {
        let got = slave.read(&mut buf).ok().filter(|&g| g > 0)?;
        let mut rest = &buf[..got];
        while !rest.is_empty() {
            let (used, event) = decoder.push(SimTime::ZERO, rest);
            rest = &rest[used..];
            if let Some(Ok(frame)) = event {
                let n = MebRepr::from_frame(&frame).emit(&mut out).ok()?;
                return Some(out[..n].to_vec());
            }
        }
    }
}
