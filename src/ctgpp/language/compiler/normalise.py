"""The normalisation stage of the offline compiler: what people write, rewritten into the wording the
query families read, before any family is tried (issue 36, item 5).

In order (:func:`normalise`; each step a small function, case kept, text that is already canonical
left unchanged):

1. Typography: dashes and quotes to ASCII, "°"-free, runs of spaces to one; contractions spelt out
   (:func:`expand_contractions`: "shouldn't" -> "should not", "won't" -> "will not", before the typo
   step could read "shouldn" as "should" and drop the "not"); asides that ask for nothing dropped
   (:func:`drop_asides`: a ticket's label, "Repro:", "Case 12 –", a parenthesis or ", which ...,"
   without a number or a side, a framing "For this study," or "On a wet evening," that names no place
   and no time, a role beside a number "the bus, vehicle 7" -> "vehicle 7", a purpose ", we want to
   test ..." or a remark "even though ..."), "without hitting anyone" -> "and must not collide", "A,
   but before that B" -> "B, then A"; a test sheet's shorthand in words (:func:`expand_shorthand`:
   "->" a sequence, "t<6s" a deadline, "<=" at most, "spd", "LC", "r=4 m", "v2 + v5").
2. Typos (:func:`correct_typos`): a word of at least 5 letters that is not in :data:`VOCABULARY` and
   is one edit away (insert, delete, substitute, or swap two neighbours) from exactly one word of it is
   replaced by that word ("chnage" -> "change", "vehicel" -> "vehicle"); a 4-letter word only by a
   swap of two neighbours ("trun" -> "turn").
3. Numbers in words (:func:`numbers_to_digits`): "thirty", "twenty-five", "one hundred", "two and a
   half", "a dozen" -> digits, where a unit follows or a vehicle noun precedes ("thirty km/h", "vehicle
   two", "a two-second gap"), both ends of a range ("fifteen to twenty-five metres"); "one lane over",
   "one by one" are left as words.
4. Units (:func:`canonical_units`): "half a minute" -> "30 seconds", "2 minutes" -> "120 seconds",
   "2-second" -> "2 seconds", "10-metre" -> "10 metres", "km/hr",
   "kmph", "kilometres an hour" -> "km/h", "miles an hour" -> "mph", "meters per second" -> "m/s".
5. Wording (:func:`canonical_wording`): bounds ("not more than", "no farther than" -> "at most"; "not
   less than", "no closer than" -> "at least"), "over one lane to the left" -> "one lane over to the
   left", "tell vehicle 3 to ..." / "I want vehicle 3 to ..." -> "vehicle 3 should ...", "keep
   vehicles 1 & 2 in their lanes" -> "vehicles 1 & 2 keep their lanes", questions and wishes ("Can
   vehicle 3 ...?", "I'd like to see car 4 ...") as requests, hedges and tags ("ideally", ", OK?")
   dropped, connectives ("subsequently", "followed by", "at the same time", "Step 2:") as "then" or
   "and", "send vehicle 3 to" -> "vehicle 3 should drive to", a distance said after a comma or "but"
   joined to the clause it qualifies ("follows vehicle 0 but no farther than 18 m back"), a negative
   subject to the prohibition for every vehicle ("nobody changes lanes" -> "every vehicle must not
   change lanes"), and a range of vehicles listed (:func:`expand_ranges`: "vehicles 1 to 4" ->
   "vehicles 1, 2, 3 and 4").
6. Lists (:func:`join_lists`): "vehicles 1, 2 and 3" -> "vehicles 1 & 2 & 3", so a list is never split
   into clauses at its commas.
"""

from __future__ import annotations

import difflib
import re

from ctgpp.behaviours import behaviours

# --- typos -------------------------------------------------------------------------------------------

_WORDS = """
vehicle vehicles agent agents truck trucks should must would could always never
change changes changing switch switches switching merge merges merging shift shifts lanes
left right rightmost leftmost lane over into onto toward towards
turn turns turning straight intersection junction crossing next uturn uturns round
collide collides colliding collision collisions crash crashes crashing smash accident accidents
behind ahead front follow follows following followed tailgate tailing distance distances
within close closer closest stay stays staying remain remains remaining keeps keeping
away least most less more further farther than between about around roughly approximately exactly
speed speeds limit limits exceed exceeds exceeding faster slower quickly slowly rapidly
drive drives driving travel travels travelling traveling cruise cruises cruising moving
accelerate accelerates accelerating acceleration decelerate decelerates decelerating brake brakes braking
maintain maintains maintaining reach reaches reaching arrive arrives arriving point destination
waypoint target stop stops stopping stopped standstill halt halts halting
second seconds metres meters metre meter minutes
everyone everybody others other every each their there where which while until after before
should side direction heading parallel same ahead offroad drivable road street pavement
avoid avoids avoiding without anything nothing everything nobody
cut cuts cutting squeeze squeezes hits bumps rear-end rear-ends rear-ending
velocity hundred thirty forty fifty sixty seventy eighty ninety twenty eleven twelve thirteen
fourteen fifteen sixteen seventeen eighteen nineteen three seven eight
goal spot along down forward their whole episode scene throughout first
gradually eventually finally afterwards then later under below above beyond
full complete
"""


def _vocabulary() -> frozenset[str]:
    words = set(_WORDS.split())
    for behaviour in behaviours().values():
        for phrasing in behaviour.phrasings:
            words.update(re.findall(r"[a-z]+", phrasing.lower()))
    return frozenset(words)


VOCABULARY = _vocabulary()
"""Words the compiler knows: its own (:data:`_WORDS`) and every behaviour's phrasings' words."""

_ENGLISH = """
wants needs would like please there these those where while whilst which whose other another
slowed slower sloww started starts starting moved moves mover drivers driver lanes turned
wheels going heading coming comes leaves leave leaving enter enters entering street streets
about around really quite rather little bigger smaller longer shorter ahead front meanwhile
scene scenes seconds minute minutes episode during whole start begin begins beginning simply
gently softly hardly quick quicker fastest slowest nearest farthest furthest behind beside
together alongside across toward along because before after until since being doing having
take takes taking took make makes making made
overtaken overtook passed followed rammed struck tailgated collided crashed bumped smashed
verge grass kerb curb sidewalk footpath median shoulder
"""


def _known() -> frozenset[str]:
    known = set(VOCABULARY) | set(_ENGLISH.split())
    for w in VOCABULARY:
        stem = w[:-1] if w.endswith("e") else w
        known.update({w + "s", w + "es", w + "d", w + "ed", stem + "ed", stem + "ing", w + "ing", w + "er",
                      w + "ly"})
    return frozenset(known)


KNOWN = _known()
"""Words never corrected: the vocabulary, their inflections and common English words."""


def _one_edit(a: str, b: str) -> bool:
    """Whether ``a`` and ``b`` differ by exactly one insertion, deletion, substitution or swap of two
    neighbouring letters (optimal string alignment distance 1)."""
    if a == b or abs(len(a) - len(b)) > 1:
        return False
    if len(a) == len(b):
        diff = [i for i in range(len(a)) if a[i] != b[i]]
        if len(diff) == 1:
            return True
        i, j = diff if len(diff) == 2 else (0, 0)
        return len(diff) == 2 and j == i + 1 and a[i] == b[j] and a[j] == b[i]
    short, long = (a, b) if len(a) < len(b) else (b, a)
    i = 0
    while i < len(short) and short[i] == long[i]:
        i += 1
    return short[i:] == long[i + 1 :]


def _swapped(a: str, b: str) -> bool:
    """Whether ``b`` is ``a`` with two neighbouring letters swapped ("trun" -> "turn")."""
    if len(a) != len(b) or a == b:
        return False
    diff = [i for i in range(len(a)) if a[i] != b[i]]
    return len(diff) == 2 and diff[1] == diff[0] + 1 and a[diff[0]] == b[diff[1]] and a[diff[1]] == b[diff[0]]


def correct_word(word: str) -> str:
    """``word`` (lower case) corrected against :data:`VOCABULARY`: itself when known, shorter than 4
    letters, or not one edit from exactly one known word (a 4-letter word: only two neighbouring
    letters swapped, "trun", "lfet"; any other edit of so short a word is too often another word)."""
    if len(word) < 4 or word in KNOWN:
        return word
    if len(word) == 4:
        near = [w for w in VOCABULARY if _swapped(word, w)]
    else:
        near = [w for w in VOCABULARY if len(w) >= 4 and _one_edit(word, w)]
    return near[0] if len(near) == 1 else word


_CONTRACTIONS = ((r"\b(w)on't\b", r"\1ill not"), (r"\b(c)an't\b", r"\1an not"),
                 (r"\b(s)han't\b", r"\1hall not"),
                 (r"\b(\w+)n't\b", r"\1 not"), (r"\b(c)annot\b", r"\1an not"),
                 # the apostrophe left out ("dont move"; not "wont", "cant": words of their own)
                 (r"\b(do|does|did|should|must|could|would|is|are|has|have)nt\b", r"\1 not"))


def expand_contractions(text: str) -> str:
    """Negative contractions spelt out: "shouldn't" -> "should not", "won't" -> "will not", "can't" and
    "cannot" -> "can not" (case of the first letter kept)."""
    for pattern, repl in _CONTRACTIONS:
        text = re.sub(pattern, repl, text, flags=re.IGNORECASE)
    return text


def correct_typos(text: str) -> str:
    """Every word of ``text`` corrected by :func:`correct_word` (case of the first letter kept)."""

    def fix(m: re.Match[str]) -> str:
        word = m.group(0)
        fixed = correct_word(word.lower())
        if fixed == word.lower():
            return word
        return fixed.capitalize() if word[0].isupper() else fixed

    return re.sub(r"[A-Za-z]+", fix, text)


# --- numbers in words --------------------------------------------------------------------------------

_SMALL = {w: i for i, w in enumerate(
    "zero one two three four five six seven eight nine ten eleven twelve thirteen fourteen fifteen "
    "sixteen seventeen eighteen nineteen".split())}
_TENS = {w: 10 * (i + 2)
         for i, w in enumerate("twenty thirty forty fifty sixty seventy eighty ninety".split())}
_NUMBER_WORD = r"(?:zero|one|two|three|four|five|six|seven|eight|nine|ten|eleven|twelve|thirteen|fourteen" \
    r"|fifteen|sixteen|seventeen|eighteen|nineteen|twenty|thirty|forty|fifty|sixty|seventy|eighty|ninety" \
    r"|hundred|dozen|a\s+half|half)"
_NUMBER_PHRASE = rf"\b{_NUMBER_WORD}(?:(?:\s+and\s+|[\s-]+){_NUMBER_WORD})*\b"
_VEHICLE_NUMBER = (  # a vehicle's number in words: "seven", "twenty-one", "twenty one"
    r"\b(?:(?:twenty|thirty|forty|fifty|sixty|seventy|eighty|ninety)"
    r"(?:[\s-](?:one|two|three|four|five|six|seven|eight|nine)\b)?"
    r"|zero|one|two|three|four|five|six|seven|eight|nine|ten|eleven|twelve|thirteen|fourteen"
    r"|fifteen|sixteen|seventeen|eighteen|nineteen)\b"
)
_UNIT_AFTER = (
    r"(?=[\s-]*(?:m\b|m/s|mps|metres?|meters?|ft\b|feet|foot|km/?h|kph|kmph|kilomet|mph|miles?"
    r"|s\b|secs?\b|seconds?\b))"
)
# both ends of a range in words: "between five and fifteen metres" (one phrase would read "five and
# fifteen" as a single number)
_RANGE_IN_WORDS = (rf"\b(between|from)\s+({_NUMBER_PHRASE})\s+(and|to)\s+({_NUMBER_PHRASE}){_UNIT_AFTER}")
# "fifteen to twenty-five metres"
_TO_RANGE_IN_WORDS = rf"\b({_NUMBER_PHRASE})\s+to\s+({_NUMBER_PHRASE}){_UNIT_AFTER}"
_VEHICLE_BEFORE = "|".join(rf"(?<=\b{noun}\s)"
                           for noun in ("vehicle", "vehicles", "car", "cars", "agent", "truck"))
_LIST_BEFORE = r"(?<=\d\s&\s)|(?<=\d,\s)|(?<=\d\sand\s)|(?<=\d,\sand\s)|(?<=\d\sor\s)"


def words_value(phrase: str) -> float | None:
    """The value of a number written in words ("twenty-five" 25, "one hundred" 100, "two and a half"
    2.5, "a dozen" 12); None when it is not one number."""
    tokens = re.split(r"[\s-]+", phrase.lower().replace("a half", "half").replace("a dozen", "dozen"))
    total, current, seen = 0.0, 0.0, False
    for tok in tokens:
        if tok == "and":
            continue
        if tok in _SMALL:
            if seen and current % 10 != 0 or (seen and current >= 10 and _SMALL[tok] >= 10):
                return None
            current += _SMALL[tok]
        elif tok in _TENS:
            if seen and current % 100 != 0:
                return None
            current += _TENS[tok]
        elif tok == "hundred":
            current = max(current, 1.0) * 100
        elif tok == "dozen":
            current = max(current, 1.0) * 12
        elif tok == "half":
            total += 0.5
        else:
            return None
        seen = True
    return total + current if seen else None


def numbers_to_digits(text: str) -> str:
    """Numbers in words before a unit or after a vehicle noun, as digits ("thirty km/h" -> "30 km/h",
    "vehicle two" -> "vehicle 2", "two and a half seconds" -> "2.5 seconds")."""

    def digits(m: re.Match[str]) -> str:
        value = words_value(m.group(0))
        if value is None:
            return m.group(0)
        return f"{value:g}"

    text = re.sub(rf"(?:{_VEHICLE_BEFORE}){_VEHICLE_NUMBER}", digits, text, flags=re.IGNORECASE)
    while True:  # the rest of a list: "vehicles two, three and four"
        unit = r"(?!\s*(?:m\b|km|mph|s\b|sec|metre|meter|ft|feet))"
        longer = re.sub(rf"(?:{_LIST_BEFORE}){_VEHICLE_NUMBER}{unit}", digits, text, flags=re.IGNORECASE)
        if longer == text:
            break
        text = longer
    text = re.sub(_RANGE_IN_WORDS, lambda m: f"{m.group(1)} {digits_of(m.group(2))} {m.group(3)} "
                  f"{digits_of(m.group(4))}", text, flags=re.IGNORECASE)
    text = re.sub(_TO_RANGE_IN_WORDS, lambda m: f"{digits_of(m.group(1))} to {digits_of(m.group(2))}", text,
                  flags=re.IGNORECASE)
    return re.sub(rf"{_NUMBER_PHRASE}{_UNIT_AFTER}", digits, text, flags=re.IGNORECASE)


def digits_of(phrase: str) -> str:
    """A number in words as digits ("fifteen" -> "15"); left as written when it is none."""
    value = words_value(phrase)
    return phrase if value is None else f"{value:g}"


# --- units and wording -------------------------------------------------------------------------------

def _minutes(m: re.Match[str]) -> str:
    return f"{float(m.group(1)) * 60:g} seconds"


_UNITS = (  # (pattern, replacement), case-insensitive, in order
    (r"\bhalf\s+a\s+minute\b", "30 seconds"),
    (r"\bhalf\s+a\s+second\b", "0.5 seconds"),
    (r"\ba\s+quarter\s+of\s+a\s+minute\b", "15 seconds"),
    (r"\b(?:a|one)\s+minute\b", "60 seconds"),
    (r"(\d+(?:\.\d+)?)\s*(?:minutes?|mins?)\b", _minutes),
    (r"(\d)-(seconds?|secs?|s|metres?|meters?|m|feet|foot|ft)\b", r"\1 \2"),
    (r"(\d)\s*(?:foot)\b", r"\1 feet"),
    (r"\bkm\s*/\s*hr?\b|\bkmph\b|\bkm\s+an\s+hour\b|\bkilomet(?:re|er)s?\s+an\s+hour\b", "km/h"),
    (r"\bmiles?\s+an\s+hour\b|\bmi\s*/\s*h\b", "mph"),
    (r"\b(?:metres?|meters?)\s*/\s*s(?:ec(?:ond)?)?\b|\bm\s*/\s*sec\b", "m/s"),
    (r"\bm\s*/\s*s\s*(?:\^\s*2|2\b|/\s*s\b)|\bm\s*s-2\b"
     r"|\b(?:metres?|meters?)\s+per\s+second\s+squared\b", "m/s²"),
)

_ONE_VEH = r"(?:(?:the\s+)?ego(?:[- ](?:vehicle|car))?|(?:vehicles?|cars?|agents?|trucks?|veh)\s*#?\d+|v\d+)"
_VEH = (  # a vehicle or a list of them ("vehicles 1, 2 and 3", "the ego and vehicle 6", "v2 + v5")
    rf"(?:{_ONE_VEH}(?:\s*(?:,|&|and|or|\+|/)\s*(?:and\s+)?(?:{_ONE_VEH}|#?\d+))*)"
)

_ALL = (r"(?:everyone|everybody|all\s+(?:the\s+)?(?:cars|vehicles|agents)|every\s+(?:car|vehicle|agent)"
        r"|each\s+(?:car|vehicle))")
_WORDING = (  # (pattern, replacement), case-insensitive, in order
    (r"\b(?:not|no)\s+more\s+than\b|\bno\s+(?:farther|further)\s+than\b|\bnot\s+(?:farther|further)\s+than\b",
     "at most"),
    (r"\b(?:not|no)\s+(?:less|closer|nearer)\s+than\b", "at least"),
    (r"\bover\s+(one|a)\s+lane\b", r"\1 lane over"),
    (r"\bto\s+(?:its|his|her|their)\s+(left|right)\b", r"to the \1"),
    (r"\b(into|in|to|onto)\s+the\s+lane\s+(?:on|to)\s+(?:its|his|her|their|the)\s+(left|right)\b",
     r"\1 the \2 lane"),
    (r"\binfront\b", "in front"),
    (r"\b(?:pls|plz)\b", "please"),
    (r"\bmore\s+(fast|quick|slow)(?:ly)?\s+th[ae]n\b", r"\1er than"),
    (r"\b(faster|slower|quicker|less|more|fewer|greater|closer|further|farther|lower|higher)\s+then\b(?=\s*(?:\d|vehicle|car|veh|agent|truck|v\d|#|the|ego))",
     r"\1 than"),
    (r"\b(?:not|no)\s+more\s+far\s+than\b", "at most"),
    (r"\bmost\s+(right|left)\s+lane\b", r"\1most lane"),
    (r",?\s+after\s+which\b|,?\s+whereupon\b|,?\s+following\s+which\b", ", then"),
    (r"[.;]?\s*\bstep\s+(?:[2-9]|two|three|four|five)\s*[:.)]\s*", ", then "),  # a later numbered step
    (r"^\s*step\s+(?:1|one)\s*[:.)]\s*", ""),
    (r"^\s*(?:\(?1[.)]|\(a\)|a\))\s+(?=[a-z])", ""),  # a list of conditions: all at once
    (r"(?<=[a-z0-9)])[.;]?\s+(?:\(?[2-9][.)]|\([b-h]\)|[b-h]\))\s+(?=[a-z])", "; "),
    (r"\b(for|during|in|within)\s+first\b", r"\1 the first"),
    (r"\b(?:not\s+before|no\s+earlier\s+than)\s+(?=(?:t\s*=\s*)?\d)", "after "),
    (r"\bon-road\b", "on the road"),
    (r"\bat(least|most)\b", r"at \1"),
    # "...; vehicle 3 then cuts in": the clause's "then" first (never an object's: "overtake ego then cut in")
    (rf"(?:^|(?<=[;,.]\s)|(?<=\band\s))({_VEH})\s+((?:shall|should|must|will)\s+)?then\s+", r"then \1 \2"),
    (r"\b(to|in|on)\s+lane\s+(cent(?:re|er)|middle)\b", r"\1 the lane \2"),
    # a sequence said another way; "followed by" only after a clause's end, never "is followed by"
    # "... by car 10, which then cuts in": the vehicle just named does it next
    (rf"({_ONE_VEH})\s*,?\s*(?:and\s+)?(?:which|who)\s+then\s+", r"\1, then \1 "),
    (r"\s*(?:,|;|\band)?\s*\b(?:subsequently|thereafter|afterwards?|after\s+this(?=,)|(?<=and\s)after\s+this)\b,?"
     r"|\s*(?:,|;)\s*(?:and\s+)?followed\s+by\b", ", then"),
    (r"\s*(?:,|;|\band)?\s*\b(?:at\s+the\s+same\s+time|simultaneously|meanwhile|concurrently)\b,?", ", and"),
    (r"\s*(?:,|;)?\s*(?:and\s+)?\bfinally\b,?", ", then"),
    (rf"\bneither\s+({_ONE_VEH})\s+nor\s+({_ONE_VEH})\s+(?:may|can|should|must|will)\s+",
     r"\1 and \2 must not "),
    (r"\bneither\s+of\s+them\s+(?:may|can|should|must|will)\s+", "they must not "),
    (r"\b(nobody|no\s+one|no\s+vehicle|not|never)\b([^,.;]*?)\s+or\s+(?=(?:leav|collid|crash|hit|chang|exceed|cross)\w*\b)",
     r"\1\2 and never "),
    (r"\bthe\s+cent(?:re|er)s?\s+of\s+(?:its|their|the)\s+lanes?\b", "the lane centre"),
    (r",\s*passing\s+(?:it|them|him|her)\s+on\s+the\s+(left|right)\b", r" on the \1"),
    (r"\s+while\s+(?:it|they)\s+(?:turns?|(?:is|are)\s+turning)\b", ""),
    (r",?\s*measured\s+along\s+", " along "),
    (r"^\s*(?:it\s+is\s+(?:required|necessary|important)|we\s+require)\s+that\s+", ""),
    (r"(,\s*then)\s+that\s+", r"\1 "),
    (r",?\s+without\s+ever\s+(?:exceeding|going\s+(?:over|above|faster\s+than))\s+", " and never exceeds "),
    (r"\bwait(?:s|ed|ing)?\s+(?:for\s+)?(\d+(?:\.\d+)?)\s*(?:s|secs?|seconds?)\b",
     r"stands still for the first \1 s"),
    (r"\b(vehicle|car|agent|truck)\s+(?:numbered|labell?ed|tagged|with\s+(?:the\s+)?(?:number|id|label))\s+",
     r"\1 "),
    (r"\b(?:one|a)\s+lane\s+(?:to\s+)?(?:the\s+)?(left|right)\b", r"one lane over to the \1"),
    # questions and wishes: "Can vehicle 3 ...?", "Could we get car 3 and car 8 to ...", "I'd like to see
    # car 4 ...", "What if the ego ...", "Let's have vehicle 11 ..."
    (rf"^\s*(?:(?:so\s+|and\s+)?(?:can|could|would|will)\s+(?:you|we|i)\s+(?:please\s+)?(?:get|make|have|let|see)"
     rf"|(?:i|we)(?:'d|\s+would)\s+(?:like|love|want)\s+to\s+see|let(?:'s|\s+us)\s+(?:have|get|make|see))"
     rf"\s+({_VEH})\s+(?:to\s+)?", r"\1 should "),
    (rf"^\s*(?:so\s+|and\s+)?(?:can|could)\s+({_VEH})\s+(?:please\s+)?", r"\1 should "),
    (rf"^\s*(?:what\s+(?:happens\s+)?if|suppose|imagine|let's\s+say)\s+({_VEH})\s+(?:had\s+to\s+|has\s+to\s+)?",
     r"\1 should "),
    (r"^\s*(?:just\s+)?(?:make\s+sure|ensure|check)\s+(?:that\s+)?", ""),
    (r"\s*\b(?:ideally|maybe|perhaps|just|kind\s+of|sort\s+of|nicely|basically|simply|sometime|somehow)\b,?",
     ""),
    (r"\blike\s+(?=\d)", ""),
    (r"^\s*(?:can|could)\s+(?:we|you)\s+(?:please\s+)?(?=keep|limit|cap|stop|prevent|avoid)", ""),
    (r"\(\s*(?:on\s+the\s+)?(left|right)(?:\s+side)?\s*\)", r"on the \1"),
    (rf"^\s*cut[- ]in\s*:\s*({_VEH})\s+(?:in\s+front\s+of|ahead\s+of)\b", r"\1 cuts in front of"),
    (r",\s*(?:at\s+)?(\d+(?:\.\d+)?\s*(?:m/s|km/h|mph|kph))\s+(on\s+the\s+way|en\s+route)\b", r" at \1 \2"),
    (r"\btol(?:erance)?\b\.?", "tolerance"),
    (r"\s*,\s*(?:ok|okay|yeah|yes|right|please|thanks|thank\s+you|too|as\s+well)\s*[?.!]*\s*$"
     r"|\s+(?:please|thanks|too|as\s+well)\s*[?.!]*\s*$", ""),
    (r"\bin\s+the\s+first\s+(?=\d)", "within the first "),
    (rf"^\s*(?:please\s+)?(?:i\s+want|i'd\s+like|i\s+would\s+like|we\s+want|we'd\s+like|tell|ask|get|make"
     rf"|have|let|force|i\s+need|we\s+need)\s+({_VEH})\s+to\s+", r"\1 should "),
    (rf"^\s*(?:please\s+)?(?:send|bring|take|route|steer|direct)\s+({_VEH})\s+", r"\1 should drive "),
    (rf"^\s*(?:please\s+)?(?:i|we)\s+(?:want|need|would\s+like)\s+({_VEH})\s+(?!to\b)", r"\1 should "),
    (rf"^\s*(?:please\s+)?(drive|move)\s+({_VEH})\s+", r"\2 should \1 "),
    (rf"\bkeep\s+({_VEH})\s+in\s+(?:its|their|the)\s+(?:own\s+|current\s+)?lanes?\b",
     r"\1 keep their lanes"),
    (rf"\bkeep\s+({_VEH}|{_ALL})\s+(?=(?:on|inside|within|under|below|off|away|out|at)\b)", r"\1 keep "),
    (r"\bkeep\s+lanes\b", "keep their lanes"),
    (r"\bkeep\w*\s+off\s+the\s+(?:verge|grass|kerb|curb|sidewalk|footpath|pavement|shoulder)\b",
     "stay on the road"),
    (r"\s*[-,;]?\s*\b(?:and\s+)?(?:no|not|never)\s+(?:driving|drive|drives|going)\s+(?:onto|on|into)\s+the\s+"
     r"(?:verge|grass|kerb|curb|sidewalk|footpath|shoulder)\b", " and never leave the road"),
    (r"\b(stay\w*|keep\w*|remain\w*|is|drives?|driving)\s+(left|right)\s+of\b", r"\1 on the \2 of"),
    (r"\bon\s+(left|right)(\s+side|\s+lane)\b", r"on the \1\2"),
    (rf"({_ONE_VEH})\s+(rear-ended|rear\s+ended|hit|overtaken|passed|cut\s+off|rammed|struck|tailgated)\s+by\b",
     r"\1 gets \2 by"),
    (rf"^\s*(?:please\s+)?({_VEH})\s*[,:|]\s*(?!(?:and|or|{_NUMBER_WORD})\b)(?=[a-z])",
     r"\1 should "),
    (r"\bkeep(s?)\s+(?:inside|within)\s+", r"stay\1 within "),
    (r"\b(should|must|will)\s+straight\b", r"\1 go straight"),
)


def canonical_units(text: str) -> str:
    """Hyphenated quantities split, speed units in the spelling the compiler reads."""
    for pattern, repl in _UNITS:
        text = re.sub(pattern, repl, text, flags=re.IGNORECASE)
    return text


# a clause whose subject is a negative quantifier ("no vehicle", "nobody", "none of the cars"), its
# optional modal and its verb
_NO_ONE = re.compile(
    r"(^|[,;]\s*|\b(?:and|but|while)\s+)"
    r"(?:no\s+(?:vehicle|car|agent|truck)s?|nobody|no\s*-?\s*one|none\s+of\s+(?:the|them)(?:\s+(?:vehicles|cars))?)"
    r"\s+(?:(?:should|must|may|can|will|shall|is\s+allowed\s+to)\s+)?([a-z]+)\b",
    re.IGNORECASE,
)
_IRREGULAR = {"goes": "go", "does": "do", "has": "have", "is": "be"}


def _base_form(verb: str) -> str:
    """The base form of a verb in the third person singular ("changes" -> "change", "switches" ->
    "switch", "tries" -> "try", "goes" -> "go"); other words unchanged."""
    low = verb.lower()
    if low in _IRREGULAR:
        return _IRREGULAR[low]
    if re.search(r"(?:ss|sh|ch|x|z)es$", low):
        return verb[:-2]
    if re.search(r"[^aeiou]ies$", low):
        return verb[:-3] + "y"
    if low.endswith("s") and not low.endswith("ss"):
        return verb[:-1]
    return verb


def negative_subjects(text: str) -> str:
    """"no vehicle changes lanes", "nobody should stop", "none of the cars speeds" -> "every vehicle must
    not change lanes": a negative quantifier is the prohibition for every vehicle, which each behaviour
    that can be denied reads (and those that cannot refuse, as they would for "every vehicle")."""

    def every(m: re.Match[str]) -> str:
        return f"{m.group(1)}every vehicle must not {_base_form(m.group(2))}"

    return _NO_ONE.sub(every, text)


# an aside that asks for nothing: a parenthesis or a ", which ...," remark without a number, and a
# framing phrase before the first comma ("For this study, ...", "To test the brakes, ..."); one with a
# number is kept (and refused if no part reads it), as is one that names a place on the map
_PLACE = r"intersection|junction|crossing|crosswalk|light|sign|lane|road|roundabout|corner|kerb|curb|shoulder"
_SAYS_WHERE = "left|right|lane|side|behind|ahead|front"
_TIME_WORDS = (r"first|last|seconds?|secs?|minutes?|mark|zero|one|two|three|four|five|six|seven|eight"
               r"|nine|ten|eleven|twelve|fifteen|twenty|thirty|half|quarter")
_ASIDES = (
    # a ticket's label before a colon ("Repro:", "Setup:", "Test plan:", "Bug #412:"), never a vehicle
    re.compile(r"^\s*(?!(?:vehicles?|cars?|agents?|trucks?|veh|the\s+ego|ego)\b)[a-z][a-z ]{0,20}?"
               r"(?:\s*#\d+|(?<=[a-z]{2})\s+\d+(?:\.\d+)*)?\s*:\s+", re.IGNORECASE),
    # a test case's number before a dash, a bar or a colon ("Case 12 –", "TC-031 |")
    re.compile(r"^\s*(?:case|tc|test(?:\s+case)?|scenario|row|id|req)[\s#-]*\d+\s*[-–:|.)]\s*",
               re.IGNORECASE),
    # a remark in brackets, never one that says a side, a lane or a place ("(left side)" is the overtake's)
    re.compile(rf"\s*\((?=[^()]*[a-z])(?![^()]*\b(?:{_SAYS_WHERE})\b)[^()\d]*\)"
               rf"|\s*\[(?=[^\[\]]*[a-z])(?![^\[\]]*\b(?:{_SAYS_WHERE})\b)[^\[\]\d]*\]", re.IGNORECASE),
    # a relative clause that asks for nothing (", which is initially parked,"); never one that does
    re.compile(r",\s*(?:which|who)\s+(?![^,]*\b(?:then|cut|overtak|pass|stop|turn|chang|collid|crash|hit|follow"
               r"|merg|slow|speed|accelerat|brak|reach|driv|go|keep|stay)\w*)[^,\d]*(?:,|(?=[.!?]?\s*$))",
               re.IGNORECASE),
    re.compile(rf"^\s*(?:for|in|to|on|at|during|as\s+part\s+of|whatever)\b(?![^,]*\b(?:{_PLACE}|{_TIME_WORDS})\b)"
               r"[^,\d]*,\s*", re.IGNORECASE),
    # a sentence that only names a role ("Vehicle 4 is the lead car.")
    re.compile(r"^\s*(?:vehicle|car|agent|truck)\s+\d+\s+is\s+(?:the|a|an)\s+[a-z -]+\.\s+", re.IGNORECASE),
    # a remark on conditions ("even though the road is icy")
    re.compile(r",?\s*\b(?:even\s+though|although|though|because|since)\b[^,.;\d]*(?=[,.;!?]|$)",
               re.IGNORECASE),
    re.compile(r"^\s*first(?:ly)?\s*,\s*", re.IGNORECASE),
)
# why the request is made ("- we're testing passenger comfort", ", so we can test the braking"): asks
# for nothing; never with a number (a number is read or refused)
_PURPOSE = re.compile(
    r"\s*(?:[,;]|\s-|\s–)?\s*\b(?:so\s+(?:that\s+)?(?:we|i|you)\s+can|we\s+want\s+to|we\s+are\s+(?:testing|trying)"
    r"|i\s+am\s+(?:testing|trying)|to\s+(?:test|check|stress|exercise)|for\s+(?:testing|a\s+test))\b[^.;\d]*"
    r"(?=[.;!?]|$)",
    re.IGNORECASE,
)
# a prohibition of collisions said as a manner ("... without hitting anyone")
_WITHOUT_HITTING = re.compile(
    r",?\s+without\s+(?:hitting|crashing\s+into|colliding\s+with|touching|striking|bumping\s+into)\s+"
    r"(?:anyone|anybody|anything|any(?:\s+other)?\s+(?:vehicle|car|agent)s?|other\s+(?:vehicles|cars|traffic))\b",
    re.IGNORECASE,
)


# a distance said after a comma or "but" about the relation just named ("vehicle 1 follows vehicle 0 but
# no farther than 18 m back", "cuts in ahead of vehicle 7, leaving at most 5 m"): part of that clause
_DISTANCE_AFTER = re.compile(
    r"\s*(?:,(?!\s*-?\d+(?:\.\d+)?\s*\))\s*(?:but\s+)?|\s+but\s+)"  # never the comma of a point "(40,8)"
    r"(?=(?:leaving|staying|keeping|with|at|no|not|within|between|under|less|gap|radius|buffer|clearance|tolerance"
    r"|minimum|min|maximum|max|\d)(?:[^,.;]|\.(?=\d))*?\d\s*(?:m|meters?|metres?|ft|feet)\b"
    r"(?:\s+(?:of\s+)?(?:gap|back|behind|ahead|apart|away|clearance|buffer|space|margin))?"
    r"(?:\s*,?\s+(?:for\s+the\s+first|within|by|after|until)\s+\d+(?:\.\d+)?\s*(?:s|secs?|seconds?)\b)?"
    r"\s*(?:[.!?]?\s*$|,\s*then\b|;))",
    re.IGNORECASE,
)


# braking hard on the way to a stop said in the same sentence: how it stops, which the stop is
_HARD_BRAKE_TO_STOP = re.compile(
    r"\b(?:hard\s+brak\w*|brak\w*\s+hard|slam\w*\s+on\s+(?:the\s+|its\s+)?brakes?)\s*(?:,\s*|\s+and\s+|\s+then\s+)?"
    r"(?=(?:to\s+a\s+|a\s+|comes?\s+to\s+a\s+|come\s+to\s+a\s+)?(?:full\s+|complete\s+)?stop)",
    re.IGNORECASE,
)


# "; as soon as it has done so, ..." / "once it has completed the turn, ...": the next part in turn
_ONCE_DONE = re.compile(
    r"\s*(?:,?\s*(?:and\s+)?then\s*)?[;,]?\s*(?:\band\s+)?\b(?:as\s+soon\s+as|once|after|when)\s+(?:it|they|he|she)"
    r"(?:'s|'ve|\s+(?:has|have|had|is|are))"
    r"(?:\s+(?:done\s+(?:so|that|this|it)|finished(?:\s+(?:it|that|the\s+\w+))?|completed\s+(?:it|that|the\s+\w+)"
    r"|reached\s+(?:it|this|that|the)(?:\s+speed)?)"
    r"|(?=\s*,))\s*,?\s*",  # "once it has," said short
    re.IGNORECASE,
)


# a role said beside a vehicle's number ("the bus, vehicle 7,", "a motorcyclist (vehicle 9)"): the number
_ROLE = re.compile(
    r"\b(?:the|a|an)\s+(?!(?:ego|vehicle|car|agent|truck)\b)[a-z][a-z -]{0,30}?\s*(?:,\s*|\(\s*)"
    r"((?:vehicle|car|agent|truck)\s+\d+)\s*(?:,|\)|(?=\s*[.;!?]|\s*$))", re.IGNORECASE)
# "A, but before that B": B, then A
_BEFORE_THAT = re.compile(
    r"^(?P<a>[^;]+?),?\s+(?:but\s+)?before\s+that,?\s+(?P<b>[^;]+?)\s*(?P<end>[.!?]?)\s*$", re.IGNORECASE)


def _first_things_first(m: re.Match[str]) -> str:
    """"A, but before that B" as "B, then A"; B's "it" is A's subject when A starts with one."""
    a, b = m.group("a"), m.group("b")
    subject = re.match(rf"\s*({_VEH})\b", a, re.IGNORECASE)
    if subject is not None:
        b = re.sub(r"^\s*(?:it|they)\b", subject.group(1), b, flags=re.IGNORECASE)
    return f"{b}, then {a}{m.group('end')}"


def drop_asides(text: str) -> str:
    """Asides that ask for nothing removed (:data:`_ASIDES`), braking hard into a stop left to the stop,
    "without hitting anyone" as "and must not collide"."""
    text = _ROLE.sub(r"\1", text)
    text = _BEFORE_THAT.sub(_first_things_first, text)
    for pattern in _ASIDES:
        text = pattern.sub(" ", text)
    text = _HARD_BRAKE_TO_STOP.sub("", text)
    text = _WITHOUT_HITTING.sub(" and must not collide", text)
    text = _ONCE_DONE.sub(", then ", text)
    text = _PURPOSE.sub("", text)
    return text.strip()


_SHORTHAND = (  # (pattern, replacement), case-insensitive, in order: a test sheet's notation in words
    (r"\s*(?:->|=>|→)\s*", ", then "),
    (r"\|\s*(accel\w*|acceleration|speed|spd)\s*\|", r"\1"),
    (r"(?:\bt\s*)?(?:<=|≤|<)\s*(\d+(?:\.\d+)?)\s*(?:s|secs?|seconds?)\b", r"within \1 s"),
    (r"(?:\bt\s*)?(?:>=|≥|>)\s*(\d+(?:\.\d+)?)\s*(?:s|secs?|seconds?)\b", r"after \1 s"),
    (r"\s*(?:<=|≤)\s*", " at most "),
    (r"\s*(?:>=|≥)\s*", " at least "),
    (r"\s*<\s*(?=\d)", " under "),
    (r"\s*>\s*(?=\d)", " over "),
    (r"\bspd\b|\bvel\b", "speed"),
    (r"\bdist\b", "distance"),
    (r"\baccel\s+(?=to\b)", "accelerate "),
    (r"\baccels?\b", "acceleration"),
    (r"\bdecel(?:erates?)?\s+(?=to\b)", "slows down "),
    (r"\bdecel\b", "deceleration"),
    (r"\bLC\b", "lane change"),
    (r"\bthru\b", "through"),
    (r"\bpt\b", "point"),
    (r"\bpos\b", "position"),
    (r"\bw/o\b", "without"),
    (r"\bw/\s*", "with "),
    (r"\br\s*=\s*(\d+(?:\.\d+)?)\s*m\b", r"radius \1 m"),
    (r"\s*@\s*", " at "),
    (r"\b(v\d+|(?:vehicle|car|agent|truck|veh)\s*#?\d+|ego)\s*[+/]\s*(?=v\d|veh|vehicle|car|agent|truck|the\s+ego|ego)",
     r"\1 and "),
    (r"^(\s*(?:from|after|before|within|until|by)\b[^:]{0,24}?\d\s*s\b[^:]{0,8}):\s*", r"\1, "),
    (r",\s*first\s+(?=\d+(?:\.\d+)?\s*(?:s|secs?|seconds?)\b)", " for the first "),
    (r"\bm/s\s+squared\b", "m/s²"),
)


def expand_shorthand(text: str) -> str:
    """A test sheet's notation in words: "->" a sequence, "t<6s" a deadline, "<=" at most, "spd", "LC",
    "r=4 m", "v2 + v5" (module docstring, step 1)."""
    for pattern, repl in _SHORTHAND:
        text = re.sub(pattern, repl, text, flags=re.IGNORECASE)
    return text


def canonical_wording(text: str) -> str:
    """Bounds, "over one lane", imperatives and negative subjects in the compiler's wording (module
    docstring, step 5)."""
    for pattern, repl in _WORDING:
        text = re.sub(pattern, repl, text, flags=re.IGNORECASE)
    text = _DISTANCE_AFTER.sub(" ", text)
    return negative_subjects(text)


_LIST = re.compile(
    r"\b((?:vehicles|cars|agents|trucks)\s+)(#?\d+(?:\s*(?:,\s*(?:and\s+)?|and\s+|&\s*)#?\d+)+)",
    re.IGNORECASE,
)


# "vehicles 1 to 4", "cars 2-5", "vehicles 3 through 6": a range of vehicle numbers (no unit after it)
_RANGE = re.compile(
    r"\b((?:vehicles?|cars?|agents?|trucks?|veh)\s+)#?(\d+)\s*(?:-|to|through|thru|until)\s*#?(\d+)\b"
    r"(?!\s*(?:m/s|km|mph|m\b|meters?|metres?|s\b|secs?\b|seconds?|feet|ft|%|\.\d))",
    re.IGNORECASE,
)
MAX_RANGE = 64  # a longer range of vehicle numbers is left as written (and refused, its numbers unread)
_PLURAL = {"veh": "vehicles", "vehicle": "vehicles", "car": "cars", "agent": "agents", "truck": "trucks"}


def expand_ranges(text: str) -> str:
    """"vehicles 1 to 4" -> "vehicles 1, 2, 3 and 4" (a range of at most :data:`MAX_RANGE` numbers,
    low to high); anything else left as it is."""

    def listed(m: re.Match[str]) -> str:
        lo, hi = int(m.group(2)), int(m.group(3))
        if not lo < hi or hi - lo >= MAX_RANGE:
            return m.group(0)
        numbers = [str(v) for v in range(lo, hi + 1)]
        noun = m.group(1).strip()
        plural = _PLURAL.get(noun.lower(), noun)  # "veh 0 through 3": a list of vehicles
        return f"{plural} {', '.join(numbers[:-1])} and {numbers[-1]}"

    return _RANGE.sub(listed, text)


def join_lists(text: str) -> str:
    """"vehicles 1, 2 and 3" -> "vehicles 1 & 2 & 3": a list of vehicles is one subject, not clauses."""

    def joined(m: re.Match[str]) -> str:
        return m.group(1) + " & ".join(re.findall(r"#?\d+", m.group(2)))

    return _LIST.sub(joined, text)


def normalise(query: str) -> str:
    """``query`` rewritten into the compiler's wording (module docstring); already canonical text is
    returned unchanged."""
    text = query
    for fancy, plain in (("–", "-"), ("—", "-"), ("’", "'"), ("‘", "'"), ("\u00a0", " ")):
        text = text.replace(fancy, plain)
    text = re.sub(r"\bactor(s?)\b", r"agent\1", text, flags=re.IGNORECASE)  # test plans' word for a vehicle
    text = expand_contractions(text)
    text = drop_asides(text)
    text = expand_shorthand(text)
    text = correct_typos(text)
    text = numbers_to_digits(text)
    text = canonical_units(text)
    text = canonical_wording(text)
    text = expand_ranges(text)
    text = join_lists(text)
    return re.sub(r"[ \t]{2,}", " ", text).strip()


def original_span(read_as: str, query: str, span: tuple[int, int]) -> tuple[int, int]:
    """The span of ``query`` that ``span`` of its normalised form ``read_as`` came from (a rewritten
    piece maps to the whole piece it replaced)."""
    start, end = span
    ops = difflib.SequenceMatcher(None, read_as, query, autojunk=False).get_opcodes()
    lo, hi = 0, len(query)
    for tag, i1, i2, j1, _ in ops:
        if i1 <= start < i2 or (start == i2 == len(read_as)):
            lo = j1 + (start - i1) if tag == "equal" else j1
            break
    for tag, i1, i2, j1, j2 in ops:
        if i1 < end <= i2:
            hi = j1 + (end - i1) if tag == "equal" else j2
            break
    return lo, max(hi, lo)
