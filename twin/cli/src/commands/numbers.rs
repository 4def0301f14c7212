//! Numbers on the command line. Every numeric option takes a leading minus
//! (clap would take `-5` for a flag and advise `-- -5`, which then fails),
//! and one that cannot be negative refuses it in words: `--duration -5`
//! gets "must be above 0, got -5".

/// Any finite number: set points, gains, offsets.
pub fn number(text: &str) -> Result<f64, String> {
    let v: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("must be a number, got `{text}`"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("must be a finite number, got `{text}`"))
    }
}

/// A number above 0: durations, periods, rates.
pub fn above_zero(text: &str) -> Result<f64, String> {
    let v = number(text)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!("must be above 0, got {text}"))
    }
}

/// A number of 0 or more: delays and timeouts where 0 means none.
pub fn zero_or_more(text: &str) -> Result<f64, String> {
    let v = number(text)?;
    if v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("must be 0 or more, got {text}"))
    }
}

/// Integer types a count or a seed is read into.
pub trait Whole: Sized + TryFrom<u128> {
    const MAX: u128;
}

macro_rules! whole {
    ($($t:ty),*) => {$(
        impl Whole for $t {
            const MAX: u128 = <$t>::MAX as u128;
        }
    )*};
}
whole!(u8, u16, u32, u64, usize);

/// A whole number from 0 to the type's largest: counts, seeds, baud rates.
pub fn whole<T: Whole>(text: &str) -> Result<T, String> {
    let t = text.trim();
    let out_of_range = || format!("must be a whole number from 0 to {}, got {text}", T::MAX);
    if let Ok(v) = t.parse::<i128>() {
        return u128::try_from(v)
            .ok()
            .filter(|&v| v <= T::MAX)
            .and_then(|v| T::try_from(v).ok())
            .ok_or_else(out_of_range);
    }
    if t.parse::<f64>().is_ok() {
        return Err(format!("must be a whole number, got {text}"));
    }
    Err(format!("must be a whole number, got `{text}`"))
}

/// Lets every option of `cmd` and of its subcommands take a leading minus
/// as a number, so the parsers above can judge it.
pub fn take_negative_numbers(cmd: clap::Command) -> clap::Command {
    cmd.mut_args(|a| {
        if a.get_action().takes_values() {
            a.allow_negative_numbers(true)
        } else {
            a
        }
    })
    .mut_subcommands(take_negative_numbers)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_judged_in_words() {
        assert_eq!(number("-5"), Ok(-5.0));
        assert_eq!(above_zero("-5"), Err("must be above 0, got -5".into()));
        assert_eq!(zero_or_more("0"), Ok(0.0));
        assert_eq!(
            zero_or_more("-0.5"),
            Err("must be 0 or more, got -0.5".into())
        );
        assert_eq!(number("fast"), Err("must be a number, got `fast`".into()));
        assert_eq!(whole::<u32>("9600"), Ok(9600));
        assert_eq!(
            whole::<u8>("-1"),
            Err("must be a whole number from 0 to 255, got -1".into())
        );
        assert_eq!(
            whole::<u8>("2.5"),
            Err("must be a whole number, got 2.5".into())
        );
    }
}
